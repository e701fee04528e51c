//! A data zip unpacked once into a folder keyed by the zip's SHA-256, through a temporary folder renamed when
//! whole. No entry may leave the folder (absolute paths, `..`), links are refused, and the number of entries and
//! the bytes written are bounded — counted while writing, not taken from the zip's headers.

use crate::error::{io, Error, Result};
use sha2::Digest;
use std::io::{Read, Write};
use std::path::{Component, Path, PathBuf};

/// Bounds on what a zip may unpack to.
#[derive(Debug, Clone, Copy)]
pub struct UnpackLimits {
    /// At most this many entries (files and folders).
    pub max_entries: usize,
    /// At most this many bytes written, all files together.
    pub max_bytes: u64,
}

impl Default for UnpackLimits {
    /// 200 000 entries, 256 GiB.
    fn default() -> Self {
        Self { max_entries: 200_000, max_bytes: 256 << 30 }
    }
}

/// [`unpack_zip_with`] under the default limits.
pub fn unpack_zip(zip: &Path, cache_root: &Path) -> Result<PathBuf> {
    unpack_zip_with(zip, cache_root, UnpackLimits::default())
}

/// Unpacks `zip` into `cache_root/<sha256 of the zip>/` unless that folder exists already, and returns it. The
/// project's data go under its own cache (`$MVSPLAT360_CACHE`, `mvsplat360_pipeline::model::cache_dir()`), e.g.
/// `cache_dir().join("data")`; a concurrent unpacker of the same zip is harmless (the first rename wins).
pub fn unpack_zip_with(zip: &Path, cache_root: &Path, limits: UnpackLimits) -> Result<PathBuf> {
    let mut f = std::fs::File::open(zip).map_err(|e| io("cannot open", zip, e))?;
    let mut h = sha2::Sha256::new();
    std::io::copy(&mut f, &mut HashWriter(&mut h)).map_err(|e| io("cannot read", zip, e))?;
    let key: String = h.finalize().iter().map(|b| format!("{b:02x}")).collect();
    let dest = cache_root.join(&key);
    if dest.is_dir() {
        return Ok(dest);
    }
    std::fs::create_dir_all(cache_root).map_err(|e| io("cannot create", cache_root, e))?;
    let tmp = crate::cache::unique_sibling(&cache_root.join(format!(".{key}")), "unpacking");
    let result = unpack_into(zip, &tmp, limits);
    if let Err(e) = result {
        let _ = std::fs::remove_dir_all(&tmp);
        return Err(e);
    }
    match std::fs::rename(&tmp, &dest) {
        Ok(()) => Ok(dest),
        // Another process finished first: its folder is as good as ours.
        Err(_) if dest.is_dir() => {
            let _ = std::fs::remove_dir_all(&tmp);
            Ok(dest)
        }
        Err(e) => {
            let _ = std::fs::remove_dir_all(&tmp);
            Err(io("cannot move the unpacked folder to", &dest, e))
        }
    }
}

struct HashWriter<'a, D: Digest>(&'a mut D);
impl<D: Digest> Write for HashWriter<'_, D> {
    fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
        self.0.update(b);
        Ok(b.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

fn unpack_into(zip: &Path, dir: &Path, limits: UnpackLimits) -> Result<()> {
    let bad = |msg: String| Error::Zip(format!("{}: {msg}; nothing was unpacked", zip.display()));
    let f = std::fs::File::open(zip).map_err(|e| io("cannot open", zip, e))?;
    let mut archive = zip::ZipArchive::new(f).map_err(|e| bad(format!("not a readable zip ({e})")))?;
    if archive.len() > limits.max_entries {
        return Err(bad(format!("{} entries, more than the {} allowed", archive.len(), limits.max_entries)));
    }
    std::fs::create_dir_all(dir).map_err(|e| io("cannot create", dir, e))?;
    let mut written = 0u64;
    for i in 0..archive.len() {
        let mut entry = archive.by_index(i).map_err(|e| bad(format!("entry {i} unreadable ({e})")))?;
        let name = entry.name().map_err(|e| bad(format!("entry {i} has an unreadable name ({e})")))?.to_string();
        let rel = safe_relative(&name).ok_or_else(|| bad(format!("entry {name:?} would be written outside the folder")))?;
        if entry.is_symlink() {
            return Err(bad(format!("entry {name:?} is a link; links are refused")));
        }
        let out = dir.join(&rel);
        if entry.is_dir() {
            std::fs::create_dir_all(&out).map_err(|e| io("cannot create", &out, e))?;
            continue;
        }
        if let Some(parent) = out.parent() {
            std::fs::create_dir_all(parent).map_err(|e| io("cannot create", parent, e))?;
        }
        let mut w = std::fs::OpenOptions::new().write(true).create_new(true).open(&out).map_err(|e| io("cannot create", &out, e))?;
        let mut buf = vec![0u8; 1 << 16];
        loop {
            let n = entry.read(&mut buf).map_err(|e| bad(format!("entry {name:?} unreadable ({e})")))?;
            if n == 0 {
                break;
            }
            written += n as u64;
            if written > limits.max_bytes {
                return Err(bad(format!("it unpacks to more than the {} bytes allowed", limits.max_bytes)));
            }
            w.write_all(&buf[..n]).map_err(|e| io("cannot write", &out, e))?;
        }
    }
    Ok(())
}

/// The entry's name as a path inside the folder: relative, without `..`, root or drive; `None` otherwise.
fn safe_relative(name: &str) -> Option<PathBuf> {
    if name.is_empty() || name.starts_with('/') || name.starts_with('\\') || name.contains('\0') || name.contains('\\') {
        return None;
    }
    let mut out = PathBuf::new();
    for c in Path::new(name).components() {
        match c {
            Component::Normal(p) => out.push(p),
            Component::CurDir => {}
            Component::ParentDir | Component::RootDir | Component::Prefix(_) => return None,
        }
    }
    (!out.as_os_str().is_empty()).then_some(out)
}

#[cfg(test)]
mod tests {
    use super::safe_relative;

    #[test]
    fn names() {
        assert!(safe_relative("a/b.torch").is_some());
        assert!(safe_relative("./a").is_some());
        for bad in ["/etc/passwd", "../x", "a/../../x", "a/..", "..\\x", "", "C:\\x"] {
            assert!(safe_relative(bad).is_none(), "{bad}");
        }
    }
}
