//! Per-scene leases in `--out/scenes/`, so that any number of processes on one output folder (cluster ranks,
//! array jobs on several nodes, a rerun next to a running job) render each scene once, with no rendezvous.
//!
//! A lease is the file `KEY.lease-G` created exclusively (`O_EXCL`, which NFS honours too). Its first line is the
//! owner's record ([`Owner`]: pid, host, start time); its second, `BEAT PROGRESS`, is rewritten at every
//! heartbeat: BEAT counts heartbeats, PROGRESS counts the owner's progress reports (stages begun, steps done). The
//! scene's current lease is its highest generation G. Nobody compares clocks across hosts: an observer keeps,
//! for every lease it waits on, when (by its own monotonic clock) it last saw the text change and the progress
//! move. The lease is stale when
//! - its owner is on this host and dead (gone, a zombie, or its pid now another process's: [`Owner::state`]):
//!   taken over at once;
//! - its text has not changed for [`Timing::stale_after`] of the observer's clock (the owner stopped
//!   heartbeating: its host died, or it was frozen);
//! - its progress has not moved for [`Timing::stall_after`] while the heartbeat goes on (a hung render).
//!
//! Taking over creates generation G + 1 exclusively, so of several processes that find the same stale lease
//! exactly one wins, and removes the older generations. At each heartbeat an owner checks its lease is still the
//! scene's current one; once it is not, [`Leases::still_mine`] says so and the owner drops the scene, writing
//! nothing. A lease is removed once its scene's record (or failure) is written.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

pub use mvsplat360_dataset::owner::Owner;
use mvsplat360_dataset::owner::State;

use crate::progress::Progress;

/// The lease clocks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Timing {
    /// How often a holder rewrites its leases.
    pub heartbeat: Duration,
    /// A lease whose text has not changed for this long (observer's clock) is taken over.
    pub stale_after: Duration,
    /// A lease whose progress has not moved for this long (observer's clock) is taken over.
    pub stall_after: Duration,
}

/// Default of [`Timing::stall_after`]: on a CPU one guided refiner step of a paper-size scene takes minutes.
pub const STALL_AFTER: Duration = Duration::from_secs(3600);

impl Timing {
    /// `eval --lease-stale`, `--lease-stall`: the heartbeat is a ninth of the stale limit (20 s by default), so a
    /// lease is only taken over after eight heartbeats missed.
    pub fn from_secs(stale_after: u64, stall_after: u64) -> Self {
        let stale_after = Duration::from_secs(stale_after.max(1));
        Self { heartbeat: stale_after / 9, stale_after, stall_after: Duration::from_secs(stall_after.max(1)) }
    }
}

impl Default for Timing {
    fn default() -> Self {
        Self::from_secs(180, STALL_AFTER.as_secs())
    }
}

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

/// A lease this process holds.
struct Held {
    path: PathBuf,
    generation: u64,
    /// Another process took it over: write nothing for the scene.
    lost: bool,
}

/// What an observer last saw of one lease, by its own clock.
struct Seen {
    text: String,
    changed: Instant,
    progress: Option<u64>,
    moved: Instant,
}

/// The leases this process holds in one folder, rewritten by a background thread while it lives.
pub struct Leases {
    dir: PathBuf,
    timing: Timing,
    held: Arc<Mutex<BTreeMap<String, Held>>>,
    seen: Mutex<HashMap<PathBuf, Seen>>,
    progress: Arc<AtomicU64>,
    stop: Arc<AtomicBool>,
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

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A lease's text: the owner's record, then `BEAT PROGRESS`.
fn lease_text(beat: u64, progress: u64) -> String {
    format!("{}\n{beat} {progress}\n", Owner::me().record())
}

/// The progress count on a lease's second line (None: not written yet, or an older lease without it).
fn progress_of(text: &str) -> Option<u64> {
    text.lines().nth(1)?.split_whitespace().nth(1)?.parse().ok()
}

/// Creates `path` exclusively with `text` already in it (a temporary file hard-linked to the name, which fails
/// when the name exists, NFS included), so that no one ever sees it empty; where the file system has no hard links,
/// created exclusively and then written.
fn create_with(path: &Path, text: &str) -> std::io::Result<()> {
    // Unique per call: threads of one process may race for the same lease.
    static CALLS: AtomicU64 = AtomicU64::new(0);
    let mut name = path.as_os_str().to_owned();
    name.push(format!(".{}", CALLS.fetch_add(1, Ordering::Relaxed)));
    let tmp = mvsplat360_dataset::atomic::partial_name(Path::new(&name));
    std::fs::write(&tmp, text)?;
    let linked = std::fs::hard_link(&tmp, path);
    let _ = std::fs::remove_file(&tmp);
    match linked {
        Err(e) if e.kind() != std::io::ErrorKind::AlreadyExists && matches!(e.raw_os_error(), Some(libc::EPERM | libc::EOPNOTSUPP | libc::ENOSYS)) => {
            use std::io::Write;
            std::fs::File::options().write(true).create_new(true).open(path)?.write_all(text.as_bytes())
        }
        r => r,
    }
}

/// Whether `held` is still `key`'s current lease (its file there, no later generation); marks it lost if not.
fn check_current(dir: &Path, key: &str, held: &mut Held) -> bool {
    if !held.lost {
        let current = lease_files(dir, key).pop();
        held.lost = current.is_none_or(|(g, p)| g != held.generation || p != held.path);
    }
    !held.lost
}

impl Leases {
    pub fn new(dir: &Path) -> Self {
        Self::with_timing(dir, Timing::default())
    }

    pub fn with_timing(dir: &Path, timing: Timing) -> Self {
        let held: Arc<Mutex<BTreeMap<String, Held>>> = Arc::default();
        let stop = Arc::new(AtomicBool::new(false));
        let progress = Arc::new(AtomicU64::new(0));
        let (h, s, p, d) = (held.clone(), stop.clone(), progress.clone(), dir.to_path_buf());
        std::thread::spawn(move || {
            let tick = timing.heartbeat.min(Duration::from_millis(250));
            let mut last = Instant::now();
            let mut beat = 0u64;
            while !s.load(Ordering::Relaxed) {
                std::thread::sleep(tick);
                if last.elapsed() < timing.heartbeat {
                    continue;
                }
                last = Instant::now();
                beat += 1;
                let text = lease_text(beat, p.load(Ordering::Relaxed));
                for (key, held) in lock(&h).iter_mut() {
                    if !check_current(&d, key, held) {
                        continue;
                    }
                    // In place, never created (a lease removed meanwhile stays removed), never truncated: the
                    // counters only grow, so a reader sees the owner's record whatever it catches.
                    if let Ok(f) = std::fs::File::options().write(true).open(&held.path) {
                        use std::os::unix::fs::FileExt;
                        let _ = f.write_all_at(text.as_bytes(), 0);
                    }
                }
            }
        });
        Self { dir: dir.to_path_buf(), timing, held, seen: Mutex::default(), progress, stop }
    }

    /// Takes `key` when no live process holds it (never blocks).
    pub fn claim(&self, key: &str) -> std::io::Result<Claim> {
        let current = lease_files(&self.dir, key).pop();
        let next = match &current {
            None => 0,
            Some((g, path)) => {
                let text = std::fs::read_to_string(path).unwrap_or_default();
                let owner = Owner::parse(text.lines().next().unwrap_or(""));
                // No record (garbled, or an older version's lease caught before it was written): held until
                // the clocks below say otherwise.
                let dead_here = owner.as_ref().is_some_and(|o| !o.is_me() && o.state() == State::Dead);
                if !(dead_here || self.observe(path, text)) {
                    return Ok(Claim::Held(owner.unwrap_or_else(unknown)));
                }
                g + 1
            }
        };
        let path = self.dir.join(format!("{key}.lease-{next}"));
        match create_with(&path, &lease_text(0, self.progress.load(Ordering::Relaxed))) {
            Ok(()) => {
                lock(&self.held).insert(key.to_string(), Held { path, generation: next, lost: false });
                // Older generations are dead weight now; their owners see they lost the scene.
                for (g, p) in lease_files(&self.dir, key) {
                    if g < next {
                        let _ = std::fs::remove_file(p);
                    }
                }
                Ok(Claim::Mine)
            }
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                let text = std::fs::read_to_string(&path).unwrap_or_default();
                Ok(Claim::Held(Owner::parse(text.lines().next().unwrap_or("")).unwrap_or_else(unknown)))
            }
            Err(e) => Err(e),
        }
    }

    /// Records what this observer sees of a lease; true when it is stale by this observer's clock.
    fn observe(&self, path: &Path, text: String) -> bool {
        let now = Instant::now();
        let progress = progress_of(&text);
        let mut seen = lock(&self.seen);
        let s = seen.entry(path.to_path_buf()).or_insert_with(|| Seen { text: text.clone(), changed: now, progress, moved: now });
        if s.text != text {
            s.text = text;
            s.changed = now;
        }
        // No progress line (an older version's lease, a garbled read): not a move.
        if progress.is_some() && s.progress != progress {
            s.progress = progress;
            s.moved = now;
        }
        now - s.changed >= self.timing.stale_after || now - s.moved >= self.timing.stall_after
    }

    /// Whether this process still holds `key` (false once another process took it over).
    pub fn still_mine(&self, key: &str) -> bool {
        lock(&self.held).get_mut(key).is_some_and(|h| check_current(&self.dir, key, h))
    }

    /// The owner's progress count, written into its leases at each heartbeat.
    pub fn progress_counter(&self) -> Arc<AtomicU64> {
        self.progress.clone()
    }

    /// Gives `key` up (its record or failure is written). A lost lease is another process's now: left alone.
    pub fn release(&self, key: &str) {
        if let Some(mut h) = lock(&self.held).remove(key) {
            if check_current(&self.dir, key, &mut h) {
                let _ = std::fs::remove_file(&h.path);
            }
        }
    }
}

impl Drop for Leases {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for (key, mut h) in std::mem::take(&mut *lock(&self.held)) {
            if check_current(&self.dir, &key, &mut h) {
                let _ = std::fs::remove_file(h.path);
            }
        }
    }
}

/// Forwards progress and counts it for the leases' heartbeat: a render that reports nothing for
/// [`Timing::stall_after`] loses its scene.
pub struct Counted<'a> {
    pub inner: &'a dyn Progress,
    pub count: Arc<AtomicU64>,
}

impl Progress for Counted<'_> {
    fn begin(&self, stage: &str, total: u64) {
        self.count.fetch_add(1, Ordering::Relaxed);
        self.inner.begin(stage, total)
    }
    fn advance(&self, n: u64) {
        self.count.fetch_add(1, Ordering::Relaxed);
        self.inner.advance(n)
    }
    fn end(&self) {
        self.count.fetch_add(1, Ordering::Relaxed);
        self.inner.end()
    }
    fn note(&self, msg: &str) {
        self.inner.note(msg)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mvsplat360_dataset::owner::host_name;
    use std::time::SystemTime;

    /// Generous: a deadline against hangs, never a measure.
    const DEADLINE: Duration = Duration::from_secs(60);

    fn gens(dir: &Path, key: &str) -> Vec<u64> {
        lease_files(dir, key).into_iter().map(|x| x.0).collect()
    }

    /// Claims until `key` is this process's, returning how long that took.
    fn claim_until_mine(l: &Leases, key: &str) -> Duration {
        let t = Instant::now();
        while l.claim(key).unwrap() != Claim::Mine {
            assert!(t.elapsed() < DEADLINE, "never taken over");
            std::thread::sleep(Duration::from_millis(10));
        }
        t.elapsed()
    }

    fn set_mtime(p: &Path, t: SystemTime) {
        std::fs::File::options().write(true).open(p).unwrap().set_modified(t).unwrap();
    }

    #[test]
    fn one_holder_and_takeover_of_dead_owners() {
        let d = tempfile::tempdir().unwrap();
        let a = Leases::new(d.path());
        let b = Leases::new(d.path());
        assert_eq!(a.claim("s1").unwrap(), Claim::Mine);
        // Another claimant (here in the same process, so not "dead"): held, by this pid.
        assert_eq!(b.claim("s1").unwrap(), Claim::Held(Owner::me()));
        assert!(a.still_mine("s1") && !b.still_mine("s1"));
        a.release("s1");
        assert!(lease_files(d.path(), "s1").is_empty());
        assert_eq!(b.claim("s1").unwrap(), Claim::Mine);
        b.release("s1");

        // A dead owner on this host (a pid beyond the kernel's maximum; the older `HOST PID` form): taken over at
        // once, as generation 1.
        std::fs::write(d.path().join("s2.lease-0"), format!("{} 4294967295\n", host_name())).unwrap();
        assert_eq!(a.claim("s2").unwrap(), Claim::Mine);
        assert_eq!(gens(d.path(), "s2"), [1]);
        // A live process on this host (the test's parent) under another start time: its pid was reused, the
        // owner is dead.
        let pid = std::os::unix::process::parent_id();
        if let Ok(Some(st)) = mvsplat360_dataset::owner::proc_stat(pid) {
            let boot = mvsplat360_dataset::owner::boot_id().unwrap_or("");
            std::fs::write(d.path().join("s4.lease-0"), format!("{pid} {} {boot}:{}\n", host_name(), st.start_ticks + 1)).unwrap();
            assert_eq!(a.claim("s4").unwrap(), Claim::Mine);
            std::fs::write(d.path().join("s5.lease-0"), format!("{pid} {} {boot}:{}\n7 3\n", host_name(), st.start_ticks)).unwrap();
            assert!(matches!(a.claim("s5").unwrap(), Claim::Held(o) if o.pid == pid));
        }
        // An empty lease (its creator has not written it yet) is held.
        std::fs::write(d.path().join("s6.lease-0"), "").unwrap();
        assert_eq!(a.claim("s6").unwrap(), Claim::Held(unknown()));
        // Dropping the holder removes what it holds.
        drop(a);
        assert!(lease_files(d.path(), "s2").is_empty());
    }

    /// An owner on another host whose clock is 10 minutes ahead or behind (its lease's mtime says so): held while
    /// its text changes, whatever the mtime; taken over once unchanged for `stale_after` of the observer's clock.
    #[test]
    fn silence_is_timed_by_the_observers_clock_not_the_owners() {
        let stale_after = Duration::from_millis(300);
        for skew in [Duration::from_secs(600), Duration::ZERO] {
            for ahead in [true, false] {
                let d = tempfile::tempdir().unwrap();
                let l = Leases::with_timing(d.path(), Timing { stale_after, ..Timing::default() });
                let p = d.path().join("s.lease-3");
                let mtime = if ahead { SystemTime::now() + skew } else { SystemTime::now() - skew };
                let mut last_change = Instant::now();
                for beat in 0..20 {
                    std::fs::write(&p, format!("77 node-b\n{beat} 5\n")).unwrap();
                    set_mtime(&p, mtime);
                    last_change = Instant::now();
                    assert_eq!(l.claim("s").unwrap(), Claim::Held(Owner { host: "node-b".into(), pid: 77, start: None }));
                    std::thread::sleep(Duration::from_millis(30));
                }
                // The owner stops: taken over, not before `stale_after` of this clock.
                claim_until_mine(&l, "s");
                assert!(last_change.elapsed() >= stale_after);
                assert_eq!(gens(d.path(), "s"), [4]);
            }
        }
    }

    /// A heartbeating owner whose progress does not move is taken over after `stall_after`; one that progresses
    /// is not.
    #[test]
    fn a_stalled_owner_is_taken_over() {
        let d = tempfile::tempdir().unwrap();
        let stall_after = Duration::from_millis(300);
        let l = Leases::with_timing(d.path(), Timing { stall_after, ..Timing::default() });
        let p = d.path().join("s.lease-0");
        let mut moved = Instant::now();
        for beat in 0..20 {
            std::fs::write(&p, format!("77 node-b\n{beat} {beat}\n")).unwrap();
            moved = Instant::now();
            assert!(matches!(l.claim("s").unwrap(), Claim::Held(_)));
            std::thread::sleep(Duration::from_millis(30));
        }
        let t = Instant::now();
        let mut beat = 100;
        loop {
            // The heartbeat goes on, the progress stays at 19.
            beat += 1;
            std::fs::write(&p, format!("77 node-b\n{beat} 19\n")).unwrap();
            if l.claim("s").unwrap() == Claim::Mine {
                break;
            }
            assert!(t.elapsed() < DEADLINE, "a stalled owner kept its lease");
            std::thread::sleep(Duration::from_millis(10));
        }
        assert!(moved.elapsed() >= stall_after);
    }

    /// The owner's heartbeat writes its progress; once its lease is taken over it knows, and neither rewrites nor
    /// removes the new owner's lease.
    #[test]
    fn an_owner_whose_lease_was_taken_over_knows_it() {
        let d = tempfile::tempdir().unwrap();
        let fast = Timing { heartbeat: Duration::from_millis(20), ..Timing::default() };
        let a = Leases::with_timing(d.path(), fast);
        assert_eq!(a.claim("s").unwrap(), Claim::Mine);
        a.progress_counter().fetch_add(41, Ordering::Relaxed);
        let p = d.path().join("s.lease-0");
        let t = Instant::now();
        while progress_of(&std::fs::read_to_string(&p).unwrap()) != Some(41) {
            assert!(t.elapsed() < DEADLINE, "no heartbeat");
            std::thread::sleep(Duration::from_millis(5));
        }
        assert_eq!(Owner::parse(std::fs::read_to_string(&p).unwrap().lines().next().unwrap()), Some(Owner::me()));
        // Another observer (as if on another host) sees no progress for its stall limit and takes over.
        let b = Leases::with_timing(d.path(), Timing { stall_after: Duration::from_millis(200), ..Timing::default() });
        claim_until_mine(&b, "s");
        assert_eq!(gens(d.path(), "s"), [1]);
        assert!(!a.still_mine("s") && b.still_mine("s"));
        // A few of a's heartbeats later: generation 0 stays gone, b's lease untouched.
        let theirs = std::fs::read_to_string(d.path().join("s.lease-1")).unwrap();
        std::thread::sleep(Duration::from_millis(200));
        assert_eq!(gens(d.path(), "s"), [1]);
        assert_eq!(std::fs::read_to_string(d.path().join("s.lease-1")).unwrap(), theirs);
        a.release("s");
        drop(a);
        assert_eq!(gens(d.path(), "s"), [1]);
        b.release("s");
        assert!(gens(d.path(), "s").is_empty());
    }

    #[test]
    fn progress_is_counted_as_it_is_forwarded() {
        let count = Arc::new(AtomicU64::new(0));
        let c = Counted { inner: &crate::progress::Silent, count: count.clone() };
        c.begin("x", 3);
        c.advance(1);
        c.note("a note is not progress");
        c.end();
        assert_eq!(count.load(Ordering::Relaxed), 3);
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
