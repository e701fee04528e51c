//! Files written so that a reader or an interrupted run only ever sees a complete one: the content goes to
//! `NAME.partial` in the same folder, which is then renamed over `NAME` (a rename within one file system is
//! atomic). A failed write removes its `.partial`; one left by a killed process is overwritten by the next write
//! and removed by the CLI's Ctrl-C handler.

use std::io;
use std::path::{Path, PathBuf};

/// Suffix of a file being written.
pub const PARTIAL_SUFFIX: &str = ".partial";

/// `path` with [`PARTIAL_SUFFIX`] appended.
pub fn partial_name(path: &Path) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(PARTIAL_SUFFIX);
    PathBuf::from(s)
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
}
