//! Files written so that a reader or an interrupted run only ever sees a complete one: the content goes to
//! `NAME.PID@HOST.partial` in the same folder, which is then renamed over `NAME` (a rename within one file system
//! is atomic). The name is the writer's own, so that several processes sharing one output folder (cluster ranks,
//! a rerun next to a running job) never write to or remove each other's temporary files. A failed write removes
//! its `.partial`; [`stale_partial`] says which leftovers are this process's or a dead one's on this host.

use std::io;
use std::path::{Path, PathBuf};

/// Suffix of a file being written.
pub const PARTIAL_SUFFIX: &str = ".partial";

/// `path` with `.PID@HOST` and [`PARTIAL_SUFFIX`] appended (this process's temporary name for it).
pub fn partial_name(path: &Path) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(format!(".{}@{}{PARTIAL_SUFFIX}", std::process::id(), host_name()));
    PathBuf::from(s)
}

/// This machine's name (`/proc/sys/kernel/hostname`, else `HOSTNAME`, else `localhost`).
pub fn host_name() -> String {
    static NAME: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    NAME.get_or_init(|| {
        let n = std::fs::read_to_string("/proc/sys/kernel/hostname").ok().or_else(|| std::env::var("HOSTNAME").ok()).unwrap_or_default();
        let n = n.trim().replace(['/', '@'], "_");
        if n.is_empty() {
            "localhost".into()
        } else {
            n
        }
    })
    .clone()
}

/// Whether process `pid` runs on this machine (Linux: its `/proc` entry; elsewhere assumed alive).
pub fn process_alive(pid: u32) -> bool {
    if cfg!(target_os = "linux") {
        Path::new("/proc").join(pid.to_string()).exists()
    } else {
        true
    }
}

/// A temporary file that may be removed: this process's, a dead process's on this host, or an old-style
/// `NAME.partial` without an owner. Another host's, or a live process's, is left alone.
pub fn stale_partial(path: &Path) -> bool {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let Some(stem) = name.strip_suffix(PARTIAL_SUFFIX) else { return false };
    let owner = stem.rsplit_once('@').and_then(|(rest, host)| Some((rest.rsplit_once('.')?.1.parse::<u32>().ok()?, host)));
    match owner {
        None => true,
        Some((pid, host)) => host == host_name() && (pid == std::process::id() || !process_alive(pid)),
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

/// A lock file `PID HOST` created exclusively: one writer per folder (a training run, a render). Removed when
/// dropped; a lock left by a dead process on this host is taken over; a live one's, or another host's (whose
/// processes cannot be seen from here), is refused with a message naming the holder.
#[derive(Debug)]
pub struct DirLock {
    path: PathBuf,
}

impl DirLock {
    /// `what` names the writer in messages ("training run", "render"); `fix` says what else the user can do.
    pub fn acquire(path: &Path, what: &str, fix: &str) -> Result<Self, String> {
        for _ in 0..2 {
            match std::fs::OpenOptions::new().write(true).create_new(true).open(path) {
                Ok(mut f) => {
                    use std::io::Write;
                    writeln!(f, "{} {}", std::process::id(), host_name()).map_err(|e| format!("{}: {e}", path.display()))?;
                    return Ok(Self { path: path.to_path_buf() });
                }
                Err(e) if e.kind() == io::ErrorKind::AlreadyExists => {
                    // `PID HOST` (an older lock holds the pid only: this host's).
                    let text = std::fs::read_to_string(path).unwrap_or_default();
                    let mut parts = text.split_whitespace();
                    let pid = parts.next().and_then(|s| s.parse::<u32>().ok());
                    let host = parts.next().map(str::to_string).unwrap_or_else(host_name);
                    if host != host_name() {
                        return Err(format!(
                            "{}: a {what} on {host} (process {}) holds this folder; its state cannot be seen from here — \
                             wait for it, or delete the file if that {what} is gone",
                            path.display(),
                            pid.map_or("?".into(), |p| p.to_string())
                        ));
                    }
                    if let Some(pid) = pid.filter(|&p| cfg!(target_os = "linux") && process_alive(p)) {
                        return Err(format!(
                            "{}: another {what} (process {pid}) is writing to this folder; wait for it, stop it, or {fix} \
                             (delete the file if process {pid} is not a {what})",
                            path.display()
                        ));
                    }
                    // Left by a process that was killed: take it over.
                    std::fs::remove_file(path).map_err(|e| format!("{}: {e}", path.display()))?;
                }
                Err(e) => return Err(format!("{}: {e}", path.display())),
            }
        }
        Err(format!("{}: could not take the lock; retry", path.display()))
    }
}

impl Drop for DirLock {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let me = partial_name(&dir.path().join("a.png"));
        assert!(me.to_string_lossy().ends_with(&format!("a.png.{}@{}.partial", std::process::id(), host_name())));
        assert!(stale_partial(&me));
        // A live process on this host (the parent of this test, pid 1 in a container: both exist).
        let live = std::os::unix::process::parent_id();
        assert!(!stale_partial(&dir.path().join(format!("a.png.{live}@{}.partial", host_name()))));
        // A pid beyond the kernel's maximum is dead.
        assert!(stale_partial(&dir.path().join(format!("a.png.4294967295@{}.partial", host_name()))));
        // Another host's is never this process's to remove; the old owner-less name is.
        assert!(!stale_partial(&dir.path().join("a.png.7@other-node.partial")));
        assert!(stale_partial(&dir.path().join("a.png.partial")));
        assert!(!stale_partial(&dir.path().join("a.png")));
    }
}
