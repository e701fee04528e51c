//! Files written so that a reader or an interrupted run only ever sees a complete one: the content goes to
//! `NAME.PID-TICKS@HOST.partial` in the same folder, which is then renamed over `NAME` (a rename within one file
//! system is atomic). The name is the writer's own ([`Owner`]: pid and start ticks, host), so that several processes
//! sharing one output folder (cluster ranks, a rerun next to a running job) never write to or remove each other's
//! temporary files. A failed write removes its `.partial`; [`stale_partial`] says which leftovers are this
//! process's or a dead one's on this host. [`DirLock`] is the one-writer-per-folder lock.

use std::io;
use std::path::{Path, PathBuf};

pub use crate::owner::host_name;
use crate::owner::{Owner, Start, State};

/// Suffix of a file being written.
pub const PARTIAL_SUFFIX: &str = ".partial";

/// `path` with `.PID-TICKS@HOST` (`.PID@HOST` where the start ticks are unknown: off Linux) and
/// [`PARTIAL_SUFFIX`] appended: this process's temporary name for it.
pub fn partial_name(path: &Path) -> PathBuf {
    let me = Owner::me();
    let mut s = path.as_os_str().to_owned();
    match &me.start {
        Some(st) => s.push(format!(".{}-{}@{}{PARTIAL_SUFFIX}", me.pid, st.ticks, me.host)),
        None => s.push(format!(".{}@{}{PARTIAL_SUFFIX}", me.pid, me.host)),
    }
    PathBuf::from(s)
}

/// The owner a temporary name records: `NAME.PID-TICKS@HOST.partial`, or the older `NAME.PID@HOST.partial`.
/// None: not a `.partial` of an owner (`NAME.partial`, another name).
fn partial_owner(name: &str) -> Option<Option<Owner>> {
    let stem = name.strip_suffix(PARTIAL_SUFFIX)?;
    let owner = stem.rsplit_once('@').and_then(|(rest, host)| {
        let tag = rest.rsplit_once('.')?.1;
        let (pid, ticks) = match tag.split_once('-') {
            Some((pid, ticks)) => (pid, Some(ticks.parse::<u64>().ok()?)),
            None => (tag, None),
        };
        Some(Owner { pid: pid.parse().ok()?, host: host.to_string(), start: ticks.map(|ticks| Start { boot: None, ticks }) })
    });
    Some(owner)
}

/// A temporary file that may be removed: this process's, a dead process's on this host (gone, a zombie, or its
/// pid now another process's: [`Owner::state`]), or an old-style `NAME.partial` without an owner. Another host's,
/// or a live process's, is left alone.
pub fn stale_partial(path: &Path) -> bool {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    match partial_owner(&name) {
        None => false,
        Some(None) => true,
        Some(Some(owner)) => owner.is_me() || owner.state() == State::Dead,
    }
}

/// Write `path` through `write(temporary path)`, then rename it into place; on failure nothing is left behind
/// and `path` keeps its previous content.
pub fn write_atomic(path: &Path, write: impl FnOnce(&Path) -> io::Result<()>) -> io::Result<()> {
    let tmp = partial_name(path);
    let done = write(&tmp).and_then(|()| std::fs::rename(&tmp, path));
    if done.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    done
}

/// [`write_atomic`] of bytes, synced to disk before the rename (for records that must survive a power loss:
/// logs, reports).
pub fn write_bytes_synced(path: &Path, bytes: &[u8]) -> io::Result<()> {
    write_atomic(path, |tmp| {
        use std::io::Write;
        let mut f = std::fs::File::create(tmp)?;
        f.write_all(bytes)?;
        f.sync_all()
    })
}

/// Flushes a folder's entries (names created, renamed or removed in it) to disk, so that a rename survives a power
/// loss; best effort (a file system without it keeps what it can).
pub fn sync_dir(dir: &Path) {
    if let Ok(f) = std::fs::File::open(dir) {
        let _ = f.sync_all();
    }
}

/// The SHA-256 of a file's content, hex (streamed: any size).
pub fn sha256_file(p: &Path) -> io::Result<String> {
    use io::Read;
    use sha2::Digest;
    let mut f = std::fs::File::open(p)?;
    let mut h = sha2::Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
    }
    Ok(h.finalize().iter().map(|b| format!("{b:02x}")).collect())
}

/// One writer per folder (a training run, a render): a kernel lock on a lock file (`.render/lock`, `train.lock`),
/// held for the [`DirLock`]'s life.
///
/// - **The lock.** `flock(LOCK_EX | LOCK_NB)` on the lock file, opened without truncating it and kept open. The
///   kernel releases it when its holder's descriptor closes: when the lock is dropped, or when the process dies
///   however it dies (SIGKILL, a crash; a zombie its parent has not reaped holds no descriptors). The descriptor is
///   close-on-exec (Rust's `std` opens every file with `O_CLOEXEC`; a test checks the flag), so a child it starts
///   (COLMAP, ffmpeg) never holds the lock, during or after its parent's life. A `flock` belongs to the open file,
///   not the process: two `DirLock`s in one process exclude each other like two processes.
/// - **The record** the holder writes once it has the lock, `PID HOST BOOT_ID:TICKS` ([`Owner::record`]), is
///   information for messages only: an empty file (its holder has not written it yet), a garbled one, or one
///   naming a dead or reused pid blocks nothing, and a file that is locked blocks whatever it says. Nobody ever
///   removes a lock file that they do not hold: a taker locks the existing file in place, then truncates it and
///   writes its record. The one exception is a record naming **another host** in a file this host can lock: it is
///   refused, naming that host, as before (see NFS below); the user deletes the file if that run is gone.
/// - **Unlock** removes the file while still holding the lock, then closes it. A taker that opened the file
///   before the removal gets the lock on the removed file, so after every `flock` it checks that the path still
///   names the file it locked (`fstat` against `stat`: device and inode) and else starts over.
///
/// **NFS and other shared file systems.** Since Linux 2.6.12 an NFS client emulates `flock` with a POSIX lock on
/// the whole file, which the server arbitrates (NLM/`lockd` for NFSv3, the protocol itself for v4): the lock then
/// holds across hosts, and a holder's lock goes when its process dies; if its machine dies, when its NFSv4 lease
/// runs out (about 90 s), or, NFSv3, when that machine boots again and its status monitor tells the server. Where the server offers no locking the `flock` fails (`ENOLCK`,
/// "No locks available"; `ENOSYS`/`EOPNOTSUPP` on Lustre without `-o flock`) and `acquire` fails with a message
/// saying so. Where locks are only local to each client (NFSv3 mounted `nolock` or `local_lock=flock|all`,
/// Lustre `localflock`, some parallel file systems), another host's lock cannot be seen: there the record is
/// what refuses a folder another host holds, as before the kernel lock (a killed run's file on another host is
/// deleted by hand). Unlinking an open file on NFS leaves a `.nfsXXXX` file beside it until it is closed, at once.
///
/// Off Unix (no `flock`): the file is created exclusively and an existing one is refused, naming its holder.
#[derive(Debug)]
pub struct DirLock {
    path: PathBuf,
    /// The locked file, open for the lock's life (closing it unlocks).
    file: std::fs::File,
}

impl DirLock {
    /// `what` names the writer in messages ("training run", "render"); `fix` says what else the user can do.
    /// Never waits: a lock held by a live process is an error naming it (from its record).
    pub fn acquire(path: &Path, what: &str, fix: &str) -> Result<Self, String> {
        let err = |e: io::Error| format!("{}: {e}", path.display());
        // Each round that starts over follows another process's unlock: a bound only against the impossible.
        for _ in 0..1000 {
            let file = match lock::open(path) {
                Ok(f) => f,
                // Off Unix only: the file is the lock.
                Err(e) if e.kind() == io::ErrorKind::AlreadyExists => {
                    let owner = Owner::parse(&std::fs::read_to_string(path).unwrap_or_default());
                    return Err(format!("{} (delete the file if no {what} runs)", held(path, what, fix, owner)));
                }
                Err(e) => return Err(err(e)),
            };
            match lock::try_lock(&file) {
                Ok(true) => {}
                Ok(false) => return Err(held(path, what, fix, Owner::parse(&read_record(&file)))),
                Err(e) if lock::unsupported(&e) => {
                    return Err(format!(
                        "{}: this file system does not support file locks ({e}), so the {what} cannot make sure it is the \
                         only one writing here; {fix} on a local disk, or mount the file system with locking (NFS: a \
                         server with lockd, not `nolock`)",
                        path.display()
                    ))
                }
                Err(e) => return Err(err(e)),
            }
            if !lock::same_file(&file, path) {
                // Its holder removed it on unlock after we opened it: take the file that is there now, if any.
                continue;
            }
            if let Some(owner) = Owner::parse(&read_record(&file)).filter(|o| o.state() == State::Elsewhere) {
                return Err(format!(
                    "{}: a {what} on {} (process {}) holds this folder; its state cannot be seen from here — wait for \
                     it, or delete the file if that {what} is gone",
                    path.display(),
                    owner.host,
                    owner.pid
                ));
            }
            let lock = Self { path: path.to_path_buf(), file };
            // Unwritten (a full disk): dropped, so removed, as it is this lock's.
            write_record(&lock.file).map_err(err)?;
            return Ok(lock);
        }
        Err(format!("{}: could not take the lock; retry", path.display()))
    }

    /// The lock file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// The message for a lock held by a live process (`owner`: its record, if written yet).
fn held(path: &Path, what: &str, fix: &str, owner: Option<Owner>) -> String {
    let who = match &owner {
        Some(o) if o.state() == State::Elsewhere => format!("a {what} on {} (process {}) holds this folder", o.host, o.pid),
        Some(o) => format!("another {what} (process {}) is writing to this folder", o.pid),
        None => format!("another {what} is writing to this folder (it has just started: its process is not recorded yet)"),
    };
    format!("{}: {who}; wait for it, stop it, or {fix}", path.display())
}

/// The record in a lock file (its first 4 KiB; unreadable: empty).
fn read_record(file: &std::fs::File) -> String {
    use io::Read;
    let mut text = Vec::new();
    let _ = lock::reader(file).take(4096).read_to_end(&mut text);
    String::from_utf8_lossy(&text).into_owned()
}

/// Replaces a locked file's content with this process's record.
fn write_record(file: &std::fs::File) -> io::Result<()> {
    use io::{Seek, Write};
    let mut f = file;
    f.set_len(0)?;
    f.seek(io::SeekFrom::Start(0))?;
    f.write_all(format!("{}\n", Owner::me().record()).as_bytes())
}

#[cfg(unix)]
mod lock {
    use std::io;
    use std::os::fd::AsRawFd;
    use std::os::unix::fs::MetadataExt;
    use std::path::Path;

    /// Opens (creates if need be) the lock file, never truncating it: it may be a live holder's. Close-on-exec, as
    /// `std` opens every file.
    pub fn open(path: &Path) -> io::Result<std::fs::File> {
        std::fs::OpenOptions::new().read(true).write(true).create(true).truncate(false).open(path)
    }

    /// `flock(LOCK_EX | LOCK_NB)`: Ok(false) when another open file holds it.
    pub fn try_lock(file: &std::fs::File) -> io::Result<bool> {
        loop {
            // SAFETY: a valid descriptor, owned by `file` for the call.
            if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } == 0 {
                return Ok(true);
            }
            let e = io::Error::last_os_error();
            match e.raw_os_error() {
                Some(libc::EINTR) => continue,
                Some(libc::EWOULDBLOCK) => return Ok(false),
                _ => return Err(e),
            }
        }
    }

    /// The file system offers no locks.
    pub fn unsupported(e: &io::Error) -> bool {
        matches!(e.raw_os_error(), Some(libc::ENOLCK | libc::ENOSYS | libc::EOPNOTSUPP))
    }

    /// Whether `path` still names the open `file` (device and inode).
    pub fn same_file(file: &std::fs::File, path: &Path) -> bool {
        match (file.metadata(), std::fs::metadata(path)) {
            (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
            _ => false,
        }
    }

    /// Reads from the start without moving the file's offset.
    pub fn reader(file: &std::fs::File) -> impl io::Read + '_ {
        struct At<'a>(&'a std::fs::File, u64);
        impl io::Read for At<'_> {
            fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
                use std::os::unix::fs::FileExt;
                let n = self.0.read_at(buf, self.1)?;
                self.1 += n as u64;
                Ok(n)
            }
        }
        At(file, 0)
    }
}

#[cfg(not(unix))]
mod lock {
    use std::io;
    use std::path::Path;

    /// No `flock`: the file is created exclusively, and an existing one is a holder's.
    pub fn open(path: &Path) -> io::Result<std::fs::File> {
        std::fs::OpenOptions::new().read(true).write(true).create_new(true).open(path)
    }

    pub fn try_lock(_: &std::fs::File) -> io::Result<bool> {
        Ok(true)
    }

    pub fn unsupported(_: &io::Error) -> bool {
        false
    }

    pub fn same_file(_: &std::fs::File, path: &Path) -> bool {
        path.exists()
    }

    pub fn reader(file: &std::fs::File) -> impl io::Read + '_ {
        file
    }
}

#[cfg(unix)]
impl std::os::fd::AsRawFd for DirLock {
    /// The locked file's descriptor (close-on-exec).
    fn as_raw_fd(&self) -> std::os::fd::RawFd {
        self.file.as_raw_fd()
    }
}

impl Drop for DirLock {
    fn drop(&mut self) {
        // Removed while still locked (the file closes, and unlocks, after this), and only while the path still
        // names the file this lock holds.
        if lock::same_file(&self.file, &self.path) {
            let _ = std::fs::remove_file(&self.path);
        }
    }
}

/// An exclusive lock on `path` held for the guard's life, waited for: one process at a time does the work it
/// guards (one conversion into a shared cache), the others then find it done. The file stays (removing it would
/// let a waiter lock an unlinked file); `on_wait` runs once if another holds it. Off Unix: no lock.
pub struct WaitLock {
    _file: std::fs::File,
}

pub fn wait_lock(path: &Path, on_wait: impl FnOnce()) -> io::Result<WaitLock> {
    let file = lock::open(path).or_else(|e| if e.kind() == io::ErrorKind::AlreadyExists { std::fs::File::open(path) } else { Err(e) })?;
    #[cfg(unix)]
    if !lock::try_lock(&file)? {
        on_wait();
        use std::os::fd::AsRawFd;
        loop {
            // SAFETY: a valid descriptor, owned by `file` for the call.
            if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX) } == 0 {
                break;
            }
            let e = io::Error::last_os_error();
            if e.raw_os_error() != Some(libc::EINTR) {
                return Err(e);
            }
        }
    }
    #[cfg(not(unix))]
    let _ = on_wait;
    Ok(WaitLock { _file: file })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_wait_lock_is_waited_for() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.lock");
        let first = wait_lock(&p, || panic!("free")).unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        let p2 = p.clone();
        let waiter = std::thread::spawn(move || {
            let mut waited = false;
            let _l = wait_lock(&p2, || waited = true).unwrap();
            tx.send(()).unwrap();
            waited
        });
        // Held: the waiter cannot pass until it is dropped.
        assert!(rx.recv_timeout(std::time::Duration::from_millis(300)).is_err());
        drop(first);
        assert!(waiter.join().unwrap());
        assert!(p.exists());
    }

    #[test]
    fn replaces_the_file_or_leaves_it_untouched() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.json");
        write_bytes_synced(&p, b"one").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"one");
        // A failing writer that already wrote part of the temporary file: the old content stays, no leftover.
        let e = write_atomic(&p, |tmp| {
            std::fs::write(tmp, b"tw")?;
            Err(io::Error::other("disk full"))
        })
        .unwrap_err();
        assert_eq!(e.to_string(), "disk full");
        assert_eq!(std::fs::read(&p).unwrap(), b"one");
        assert!(!partial_name(&p).exists());
        write_atomic(&p, |tmp| std::fs::write(tmp, b"two")).unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"two");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn only_own_or_dead_owners_partials_are_stale() {
        let dir = tempfile::tempdir().unwrap();
        let h = host_name();
        let me = partial_name(&dir.path().join("a.png"));
        let tag = match &Owner::me().start {
            Some(s) => format!("{}-{}", std::process::id(), s.ticks),
            None => std::process::id().to_string(),
        };
        assert!(me.to_string_lossy().ends_with(&format!("a.png.{tag}@{h}.partial")), "{}", me.display());
        assert!(stale_partial(&me));
        // This process under the older name (pid only) is still this process's.
        assert!(stale_partial(&dir.path().join(format!("a.png.{}@{h}.partial", std::process::id()))));
        // A live process on this host (the parent of this test, pid 1 in a container: both exist), under the old
        // name and, on Linux, under its own start ticks.
        let live = std::os::unix::process::parent_id();
        assert!(!stale_partial(&dir.path().join(format!("a.png.{live}@{h}.partial"))));
        if let Ok(Some(st)) = crate::owner::proc_stat(live) {
            assert!(!stale_partial(&dir.path().join(format!("a.b.png.{live}-{}@{h}.partial", st.start_ticks))));
            // The same pid with another start time: a process that had the pid before, dead.
            assert!(stale_partial(&dir.path().join(format!("a.b.png.{live}-{}@{h}.partial", st.start_ticks + 1))));
        }
        // A pid beyond the kernel's maximum is dead.
        assert!(stale_partial(&dir.path().join(format!("a.png.4294967295@{h}.partial"))));
        assert!(stale_partial(&dir.path().join(format!("a.png.4294967295-12@{h}.partial"))));
        // Another host's is never this process's to remove; the old owner-less name is.
        assert!(!stale_partial(&dir.path().join("a.png.7@other-node.partial")));
        assert!(!stale_partial(&dir.path().join("a.png.7-99@other-node.partial")));
        assert!(stale_partial(&dir.path().join("a.png.partial")));
        assert!(!stale_partial(&dir.path().join("a.png")));
    }

    /// `std` opens files close-on-exec, so a child started while the lock is held never inherits it.
    #[cfg(unix)]
    #[test]
    fn the_lock_descriptor_is_close_on_exec() {
        use std::os::fd::AsRawFd;
        let dir = tempfile::tempdir().unwrap();
        let lock = DirLock::acquire(&dir.path().join("lock"), "render", "choose another --out").unwrap();
        // SAFETY: a valid descriptor owned by `lock`.
        let flags = unsafe { libc::fcntl(lock.as_raw_fd(), libc::F_GETFD) };
        assert!(flags >= 0 && flags & libc::FD_CLOEXEC != 0, "flags {flags}");
    }

    #[test]
    fn the_record_is_written_once_locked_and_the_file_goes_on_unlock() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("lock");
        let lock = DirLock::acquire(&p, "render", "choose another --out").unwrap();
        assert_eq!(std::fs::read_to_string(&p).unwrap(), format!("{}\n", Owner::me().record()));
        let e = DirLock::acquire(&p, "render", "choose another --out").unwrap_err();
        assert!(e.contains(&format!("another render (process {}) is writing to this folder", std::process::id())), "{e}");
        assert!(e.contains("choose another --out"), "{e}");
        drop(lock);
        assert!(!p.exists());
        // A longer record left before (garbled, of a dead process): locked in place and overwritten whole.
        std::fs::write(&p, "4294967295 a-very-long-host-name-indeed trailing garbage\n").unwrap();
        let lock = DirLock::acquire(&p, "render", "x").unwrap();
        assert_eq!(std::fs::read_to_string(&p).unwrap(), format!("{}\n", Owner::me().record()));
        drop(lock);
    }
}
