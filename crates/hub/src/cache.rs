//! The Hugging Face cache layout, as the Python client (`huggingface_hub`) writes and reads it:
//!
//! ```text
//! <cache>/models--OWNER--REPO/blobs/<etag>                 the file's bytes (<etag>.incomplete while downloading)
//! <cache>/models--OWNER--REPO/snapshots/<commit>/PATH      a relative link to ../../blobs/<etag> (one ../ more per folder)
//! <cache>/models--OWNER--REPO/refs/<revision>              the commit hash a branch or tag pointed at
//! <cache>/.locks/models--OWNER--REPO/<etag>.lock           flock'ed while the blob is written (Python's filelock)
//! ```

use crate::error::{io, Error, Result};
use crate::names::{is_commit_hash, HubFile};
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// A Hugging Face hub cache folder (`HF_HUB_CACHE`).
#[derive(Debug, Clone)]
pub struct Cache {
    root: PathBuf,
}

impl Cache {
    /// The cache at `root`.
    pub fn new(root: impl Into<PathBuf>) -> Self {
        Self { root: root.into() }
    }

    /// Its folder.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// `models--OWNER--REPO`, Python's `repo_folder_name` for a model repository.
    pub fn repo_folder(repo: &str) -> String {
        format!("models--{}", repo.replace('/', "--"))
    }

    /// `<cache>/models--OWNER--REPO`.
    pub fn repo_dir(&self, repo: &str) -> PathBuf {
        self.root.join(Self::repo_folder(repo))
    }

    /// `blobs/<etag>`.
    pub fn blob(&self, repo: &str, etag: &str) -> PathBuf {
        self.repo_dir(repo).join("blobs").join(etag)
    }

    /// `blobs/<etag>.incomplete`: the partial download, resumed by either client.
    pub fn incomplete(&self, repo: &str, etag: &str) -> PathBuf {
        self.repo_dir(repo).join("blobs").join(format!("{etag}.incomplete"))
    }

    /// `.locks/models--OWNER--REPO/<etag>.lock`.
    pub fn lock_path(&self, repo: &str, etag: &str) -> PathBuf {
        self.root.join(".locks").join(Self::repo_folder(repo)).join(format!("{etag}.lock"))
    }

    /// `snapshots/<commit>`.
    pub fn snapshot(&self, repo: &str, commit: &str) -> PathBuf {
        self.repo_dir(repo).join("snapshots").join(commit)
    }

    /// `snapshots/<commit>/PATH`.
    pub fn pointer(&self, repo: &str, commit: &str, path: &str) -> PathBuf {
        let mut p = self.snapshot(repo, commit);
        p.extend(path.split('/'));
        p
    }

    /// `refs/<revision>` (a revision with '/' makes folders, as in Python).
    pub fn ref_path(&self, repo: &str, revision: &str) -> PathBuf {
        let mut p = self.repo_dir(repo).join("refs");
        p.extend(revision.split('/'));
        p
    }

    /// The commit a revision stands for in the cache: itself if it is a commit hash, else `refs/<revision>`.
    pub fn commit_of(&self, repo: &str, revision: &str) -> Option<String> {
        if is_commit_hash(revision) {
            return Some(revision.to_string());
        }
        let s = std::fs::read_to_string(self.ref_path(repo, revision)).ok()?;
        let s = s.trim();
        (!s.is_empty()).then(|| s.to_string())
    }

    /// The cached file (or, without a path, the snapshot folder) of `file`, without any request.
    pub fn cached(&self, file: &HubFile) -> Option<PathBuf> {
        let commit = self.commit_of(&file.repo, &file.revision)?;
        let p = match &file.path {
            Some(path) => self.pointer(&file.repo, &commit, path),
            None => self.snapshot(&file.repo, &commit),
        };
        // `exists` follows the link: a link whose blob is gone is not a cached file.
        p.exists().then_some(p)
    }

    /// Records `refs/<revision>` = `commit`, atomically, when the revision is not the commit itself and the
    /// ref differs (as Python's `_cache_commit_hash_for_specific_revision`).
    pub fn write_ref(&self, repo: &str, revision: &str, commit: &str) -> Result<()> {
        if revision == commit {
            return Ok(());
        }
        let path = self.ref_path(repo, revision);
        if std::fs::read_to_string(&path).is_ok_and(|s| s == commit) {
            return Ok(());
        }
        let dir = path.parent().expect("a ref has a folder");
        std::fs::create_dir_all(dir).map_err(|e| io("cannot create", dir, e))?;
        let tmp = unique_sibling(&path, "tmp");
        std::fs::write(&tmp, commit).map_err(|e| io("cannot write", &tmp, e))?;
        std::fs::rename(&tmp, &path).map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            io("cannot write", &path, e)
        })
    }

    /// Makes `snapshots/<commit>/PATH` a relative link to `blobs/<etag>` (replacing whatever was there), and
    /// returns its path.
    pub fn link(&self, repo: &str, commit: &str, path: &str, etag: &str) -> Result<PathBuf> {
        let pointer = self.pointer(repo, commit, path);
        let depth = path.split('/').count() + 1; // up from the link's folder to the repository folder
        let target: PathBuf = std::iter::repeat_n("..", depth).collect::<PathBuf>().join("blobs").join(etag);
        if std::fs::read_link(&pointer).is_ok_and(|t| t == target) {
            return Ok(pointer);
        }
        let dir = pointer.parent().expect("a snapshot file has a folder");
        std::fs::create_dir_all(dir).map_err(|e| io("cannot create", dir, e))?;
        let tmp = unique_sibling(&pointer, "link");
        symlink(&target, &tmp).map_err(|e| io("cannot create the link", &tmp, e))?;
        std::fs::rename(&tmp, &pointer).map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            io("cannot create the link", &pointer, e)
        })?;
        Ok(pointer)
    }
}

#[cfg(unix)]
fn symlink(target: &Path, link: &Path) -> std::io::Result<()> {
    std::os::unix::fs::symlink(target, link)
}

#[cfg(not(unix))]
fn symlink(_target: &Path, _link: &Path) -> std::io::Result<()> {
    Err(std::io::Error::new(std::io::ErrorKind::Unsupported, "the Hugging Face cache layout needs symbolic links"))
}

/// `<path>.<pid>.<n>.<what>`: a name beside `path` no other process or thread uses.
pub(crate) fn unique_sibling(path: &Path, what: &str) -> PathBuf {
    static N: AtomicU64 = AtomicU64::new(0);
    let n = N.fetch_add(1, Ordering::Relaxed);
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(format!(".{}.{n}.{what}", std::process::id()));
    path.with_file_name(name)
}

/// An exclusive `flock` on a lock file, held until dropped — the lock Python's `filelock.UnixFileLock` takes, so
/// the two clients exclude each other. The file itself is left in place (as filelock does).
#[derive(Debug)]
pub struct FileLock {
    _file: File,
}

impl FileLock {
    /// Takes the lock on `path` (created if missing), waiting as long as another holder keeps it; `on_wait` is
    /// called once if it has to wait.
    pub fn acquire(path: &Path, on_wait: impl FnOnce()) -> Result<Self> {
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(|e| io("cannot create", dir, e))?;
        }
        let file =
            std::fs::OpenOptions::new().read(true).write(true).create(true).truncate(false).open(path).map_err(|e| io("cannot open the lock file", path, e))?;
        if !flock(&file, true).map_err(|e| io("cannot lock", path, e))? {
            on_wait();
            flock(&file, false).map_err(|e| io("cannot lock", path, e))?;
        }
        Ok(Self { _file: file })
    }
}

/// `flock(LOCK_EX)`; with `try_only`, `Ok(false)` when another descriptor holds it.
#[cfg(unix)]
fn flock(file: &File, try_only: bool) -> std::io::Result<bool> {
    use std::os::fd::AsRawFd;
    let op = if try_only { libc::LOCK_EX | libc::LOCK_NB } else { libc::LOCK_EX };
    loop {
        // SAFETY: a valid open descriptor; flock has no memory effects.
        if unsafe { libc::flock(file.as_raw_fd(), op) } == 0 {
            return Ok(true);
        }
        let e = std::io::Error::last_os_error();
        match e.raw_os_error() {
            Some(libc::EINTR) => continue,
            Some(libc::EWOULDBLOCK) if try_only => return Ok(false),
            _ => return Err(e),
        }
    }
}

#[cfg(not(unix))]
fn flock(_file: &File, _try_only: bool) -> std::io::Result<bool> {
    Ok(true)
}

/// A `Cache` error for a path (kept here for the modules that only need the constructor).
pub(crate) fn not_cached_hint(cache: &Cache, file: &HubFile) -> String {
    let repo_dir = cache.repo_dir(&file.repo);
    let place = match &file.path {
        Some(p) => format!("{}/snapshots/<commit>/{p} (a file or a link to blobs/), with refs/{} holding <commit>", repo_dir.display(), file.revision),
        None => format!("{}/snapshots/<commit>/, with refs/{} holding <commit>", repo_dir.display(), file.revision),
    };
    format!("place it at {place}")
}

/// Removes a file, ignoring "not found".
pub(crate) fn remove_if_present(path: &Path) -> Result<()> {
    match std::fs::remove_file(path) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(Error::Io(format!("cannot remove {}: {e}", path.display()))),
    }
}
