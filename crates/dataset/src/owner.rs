//! Who owns a lock, a lease or a temporary name: one record, [`Owner`] = host, pid and the process's start time
//! (the kernel's boot id and the process's start in clock ticks since boot, field 22 of `/proc/PID/stat`). A pid
//! alone does not name a process: the kernel hands it out again once its process is gone, and a killed process
//! that its parent has not reaped yet (a zombie) keeps its `/proc/PID` entry although it holds nothing and will
//! never run again. So an owner is alive ([`State::Alive`]) when it is on this host and a process with its pid
//! runs here, started at the recorded time, and is not a zombie (state `Z` or `X` with no thread left: a main
//! thread that exited before the others shows `Z` while they run); a pid reused by an unrelated process (another
//! start time) or a machine rebooted since (another boot id) never keeps a dead owner's claim.
//!
//! The text form is one line, `PID HOST START` with START = `BOOT_ID:TICKS` ([`Owner::record`]). Older records
//! still read: `PID HOST` and `PID` (locks: a bare pid is this host's), `HOST PID` (eval leases). Without a start
//! time only the pid can decide (alive = it runs here and is not a zombie): such a record whose pid was reused
//! still counts as alive.
//!
//! An owner on another host cannot be seen from here ([`State::Elsewhere`]): the caller decides (a lease waits
//! for its heartbeat to stop, a lock is refused naming it). Off Linux (no `/proc`) the start time is unknown and
//! every owner on this host is assumed alive: a leftover of a killed process waits for the user, as it always did.

use std::path::Path;
use std::sync::OnceLock;

/// When a process started: the boot it ran in and its start in clock ticks since that boot.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Start {
    /// `/proc/sys/kernel/random/boot_id` of the boot it ran in (None: not recorded, as in a temporary file's name,
    /// where only the ticks fit; this boot is assumed).
    pub boot: Option<String>,
    /// Field 22 of `/proc/PID/stat` (`starttime`).
    pub ticks: u64,
}

/// A process, as locks, leases and temporary names record it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Owner {
    pub pid: u32,
    pub host: String,
    /// None: an older record, or written where the start time cannot be read (off Linux).
    pub start: Option<Start>,
}

/// What this host can tell of an [`Owner`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum State {
    /// It runs (or, off Linux or where `/proc` hides it, cannot be shown not to).
    Alive,
    /// Gone: no such process, a zombie, a reused pid, or a previous boot.
    Dead,
    /// On another host: its processes cannot be seen from here.
    Elsewhere,
}

/// The parts of `/proc/PID/stat` an owner needs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ProcStat {
    /// Field 3 (of the main thread): `R`, `S`, `D`, `T`, `Z` (zombie), `X` (dead), …
    pub state: char,
    /// Field 20: the threads not yet exited (a zombie whose threads are all gone counts 1).
    pub threads: u64,
    /// Field 22: the start in clock ticks since boot.
    pub start_ticks: u64,
}

/// Parses one `/proc/PID/stat` line. The command name (field 2, in parentheses) may hold spaces and parentheses,
/// `) (` included, so the fields are counted from the LAST `)`.
pub fn parse_stat(line: &str) -> Option<ProcStat> {
    let (_, rest) = line.rsplit_once(')')?;
    let mut fields = rest.split_whitespace();
    let state = fields.next()?.chars().next()?;
    // Fields 4..=19 come before the thread count, field 21 between it and the start time.
    let threads = fields.nth(16)?.parse().ok()?;
    let start_ticks = fields.nth(1)?.parse().ok()?;
    Some(ProcStat { state, threads, start_ticks })
}

/// `/proc/PID/stat` of `pid` (Linux). `Err` as the read failed: `NotFound` for no such process.
pub fn proc_stat(pid: u32) -> std::io::Result<Option<ProcStat>> {
    let bytes = std::fs::read(Path::new("/proc").join(pid.to_string()).join("stat"))?;
    // The command name is any bytes the process chose: only the fields after it are read.
    Ok(parse_stat(&String::from_utf8_lossy(&bytes)))
}

/// This boot's id (`/proc/sys/kernel/random/boot_id`; None off Linux).
pub fn boot_id() -> Option<&'static str> {
    static ID: OnceLock<Option<String>> = OnceLock::new();
    ID.get_or_init(|| {
        let id = std::fs::read_to_string("/proc/sys/kernel/random/boot_id").ok()?;
        let id = id.trim();
        (!id.is_empty() && !id.contains(char::is_whitespace)).then(|| id.to_string())
    })
    .as_deref()
}

/// This machine's name (`/proc/sys/kernel/hostname`, else `HOSTNAME`, else `localhost`), with `/`, `@` and white
/// space replaced by `_` (it goes into file names and one-line records).
pub fn host_name() -> String {
    static NAME: OnceLock<String> = OnceLock::new();
    NAME.get_or_init(|| {
        let n = std::fs::read_to_string("/proc/sys/kernel/hostname").ok().or_else(|| std::env::var("HOSTNAME").ok()).unwrap_or_default();
        let n = n.trim().replace(|c: char| c == '/' || c == '@' || c.is_whitespace(), "_");
        if n.is_empty() {
            "localhost".into()
        } else {
            n
        }
    })
    .clone()
}

impl Start {
    fn parse(s: &str) -> Option<Self> {
        let (boot, ticks) = s.rsplit_once(':')?;
        Some(Self { boot: (!boot.is_empty()).then(|| boot.to_string()), ticks: ticks.parse().ok()? })
    }
}

impl Owner {
    /// This process.
    pub fn me() -> Self {
        static ME: OnceLock<Owner> = OnceLock::new();
        ME.get_or_init(|| {
            let pid = std::process::id();
            let ticks = if cfg!(target_os = "linux") { proc_stat(pid).ok().flatten().map(|s| s.start_ticks) } else { None };
            Owner { pid, host: host_name(), start: ticks.map(|ticks| Start { boot: boot_id().map(str::to_string), ticks }) }
        })
        .clone()
    }

    /// Reads a record ([`Owner::record`], or an older form: see the module docs). None: empty or garbled.
    pub fn parse(text: &str) -> Option<Self> {
        let t: Vec<&str> = text.split_whitespace().collect();
        match t.as_slice() {
            [pid] => Some(Self { pid: pid.parse().ok()?, host: host_name(), start: None }),
            [pid, host] if pid.parse::<u32>().is_ok() => Some(Self { pid: pid.parse().ok()?, host: host.to_string(), start: None }),
            [host, pid] => Some(Self { pid: pid.parse().ok()?, host: host.to_string(), start: None }),
            [pid, host, start] => Some(Self { pid: pid.parse().ok()?, host: host.to_string(), start: Some(Start::parse(start)?) }),
            _ => None,
        }
    }

    /// The one-line text form, `PID HOST BOOT_ID:TICKS` (`PID HOST` without a start time).
    pub fn record(&self) -> String {
        match &self.start {
            Some(s) => format!("{} {} {}:{}", self.pid, self.host, s.boot.as_deref().unwrap_or(""), s.ticks),
            None => format!("{} {}", self.pid, self.host),
        }
    }

    /// Whether this is this process (same host and pid, and the same start time where both are known).
    pub fn is_me(&self) -> bool {
        let me = Self::me();
        self.host == me.host && self.pid == me.pid && same_start(self.start.as_ref(), me.start.as_ref())
    }

    /// Whether it runs: see the module docs.
    pub fn state(&self) -> State {
        if self.host != host_name() {
            return State::Elsewhere;
        }
        if !cfg!(target_os = "linux") {
            return State::Alive;
        }
        if let (Some(Start { boot: Some(b), .. }), Some(now)) = (&self.start, boot_id()) {
            if b != now {
                return State::Dead;
            }
        }
        match proc_stat(self.pid) {
            Ok(Some(st)) => {
                let zombie = matches!(st.state, 'Z' | 'X') && st.threads <= 1;
                let reused = self.start.as_ref().is_some_and(|s| s.ticks != st.start_ticks);
                if zombie || reused {
                    State::Dead
                } else {
                    State::Alive
                }
            }
            // Unreadable (`/proc` mounted with `hidepid`, a line this code does not know): cannot be shown dead.
            Ok(None) => State::Alive,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound || e.raw_os_error() == Some(3) => State::Dead,
            Err(_) => State::Alive,
        }
    }

    /// [`Owner::state`] is [`State::Dead`]: on this host and gone.
    pub fn is_dead(&self) -> bool {
        self.state() == State::Dead
    }
}

fn same_start(a: Option<&Start>, b: Option<&Start>) -> bool {
    match (a, b) {
        (Some(a), Some(b)) => a.ticks == b.ticks && (a.boot.is_none() || b.boot.is_none() || a.boot == b.boot),
        _ => true,
    }
}

impl std::fmt::Display for Owner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "pid {} on {}", self.pid, self.host)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `stat` line as the kernel writes it for the command `name`, state `state`, start `start`.
    fn line(pid: u32, name: &str, state: char, start: u64) -> String {
        let mid: Vec<String> = (4..=21).map(|i| (i * 3).to_string()).collect();
        format!("{pid} ({name}) {state} {} {start} 4096 55 0 0\n", mid.join(" "))
    }

    #[test]
    fn the_command_name_may_hold_spaces_and_parentheses() {
        for name in ["sleep", "a b", "x) (y", ") (", "((", "evil) R 1 2 3", ""] {
            let st = parse_stat(&line(77, name, 'S', 123456789)).unwrap_or_else(|| panic!("{name:?}"));
            assert_eq!(st, ProcStat { state: 'S', threads: 60, start_ticks: 123456789 }, "{name:?}");
        }
        assert_eq!(parse_stat(&line(9, "z) (z", 'Z', 5)).unwrap().state, 'Z');
        assert_eq!(parse_stat("12 (short) S 1 2"), None);
        assert_eq!(parse_stat("no parenthesis"), None);
    }

    /// The kernel's own line for a program named `x) (y z`.
    #[cfg(target_os = "linux")]
    #[test]
    fn a_running_command_named_with_parentheses_parses() {
        let d = tempfile::tempdir().unwrap();
        let exe = d.path().join("x) (y z");
        std::fs::copy("/bin/sleep", &exe).unwrap();
        // Another test's fork may hold the copy open for a moment (ETXTBSY).
        let mut child = (0..100)
            .find_map(|_| match std::process::Command::new(&exe).arg("30").spawn() {
                Err(e) if e.raw_os_error() == Some(libc::ETXTBSY) => {
                    std::thread::sleep(std::time::Duration::from_millis(10));
                    None
                }
                r => Some(r.unwrap()),
            })
            .unwrap();
        let text = std::fs::read_to_string(format!("/proc/{}/stat", child.id())).unwrap();
        let st = proc_stat(child.id()).unwrap().unwrap();
        child.kill().unwrap();
        child.wait().unwrap();
        assert!(text.contains("(x) (y z)"), "{text}");
        assert!(!matches!(st.state, 'Z' | 'X'), "{text}");
        assert_eq!(st.threads, 1, "{text}");
        let me = proc_stat(std::process::id()).unwrap().unwrap();
        assert!(st.start_ticks >= me.start_ticks, "{text}");
    }

    #[test]
    fn this_process_reads_as_its_own_stat_says() {
        let me = Owner::me();
        assert_eq!(me.pid, std::process::id());
        assert!(me.is_me());
        assert_eq!(me.state(), State::Alive);
        if cfg!(target_os = "linux") {
            let st = proc_stat(me.pid).unwrap().unwrap();
            assert!(matches!(st.state, 'R' | 'S'), "{st:?}");
            let start = me.start.clone().expect("a start time on Linux");
            assert_eq!(start.ticks, st.start_ticks);
            assert_eq!(start.boot.as_deref(), boot_id());
            assert_eq!(me.record(), format!("{} {} {}:{}", me.pid, host_name(), boot_id().unwrap(), st.start_ticks));
        }
        assert_eq!(Owner::parse(&me.record()), Some(me.clone()));
        assert_eq!(Owner::parse(&format!("{}\n", me.record())), Some(me));
    }

    #[test]
    fn older_records_and_garbled_ones() {
        let h = host_name();
        assert_eq!(Owner::parse("12"), Some(Owner { pid: 12, host: h.clone(), start: None }));
        assert_eq!(Owner::parse("12 node-b\n"), Some(Owner { pid: 12, host: "node-b".into(), start: None }));
        assert_eq!(Owner::parse("node-b 77\n"), Some(Owner { pid: 77, host: "node-b".into(), start: None }));
        let s = Some(Start { boot: Some("b00t".into()), ticks: 9 });
        assert_eq!(Owner::parse("5 h b00t:9"), Some(Owner { pid: 5, host: "h".into(), start: s }));
        for bad in ["", "  \n", "x", "12 node-b 4", "12 node-b b:x", "1 2 3 4", "node-b x", "-1"] {
            assert_eq!(Owner::parse(bad), None, "{bad:?}");
        }
    }

    #[test]
    fn another_host_cannot_be_seen() {
        assert_eq!(Owner { pid: std::process::id(), host: "elsewhere-xyz".into(), start: None }.state(), State::Elsewhere);
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn dead_reused_rebooted_and_zombie_owners() {
        let h = host_name();
        let boot = boot_id().map(str::to_string);
        // A pid beyond the kernel's maximum.
        assert_eq!(Owner { pid: u32::MAX, host: h.clone(), start: None }.state(), State::Dead);
        // A live process (the parent of this test), under its own start time, another one, or another boot's.
        let pid = std::os::unix::process::parent_id();
        let ticks = proc_stat(pid).unwrap().unwrap().start_ticks;
        let owner = |boot: Option<String>, ticks| Owner { pid, host: h.clone(), start: Some(Start { boot, ticks }) };
        assert_eq!(owner(boot.clone(), ticks).state(), State::Alive);
        assert_eq!(owner(None, ticks).state(), State::Alive);
        assert_eq!(owner(boot.clone(), ticks + 1).state(), State::Dead);
        assert_eq!(owner(Some("another-boot".into()), ticks).state(), State::Dead);
        assert!(!owner(boot.clone(), ticks).is_me());
        // This process's pid with another start time is a process that had the pid before: dead, not me.
        let me = Owner::me();
        let earlier = Owner { start: Some(Start { boot: boot.clone(), ticks: me.start.as_ref().unwrap().ticks.wrapping_sub(1) }), ..me };
        assert!(!earlier.is_me());
        assert_eq!(earlier.state(), State::Dead);
        // A child that exited and is not reaped yet: a zombie, dead whatever its record says.
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let cpid = child.id();
        let t = std::time::Instant::now();
        let st = loop {
            let st = proc_stat(cpid).unwrap().unwrap();
            if st.state == 'Z' {
                break st;
            }
            assert!(t.elapsed() < std::time::Duration::from_secs(30), "the child never exited");
            std::thread::sleep(std::time::Duration::from_millis(2));
        };
        assert!(Path::new("/proc").join(cpid.to_string()).exists(), "a zombie keeps its /proc entry");
        let zombie = Owner { pid: cpid, host: h.clone(), start: Some(Start { boot, ticks: st.start_ticks }) };
        assert_eq!(zombie.state(), State::Dead);
        assert_eq!(Owner { start: None, ..zombie }.state(), State::Dead);
        child.wait().unwrap();
    }
}
