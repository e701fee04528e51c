//! The page's files (compiled in) and the static export.

use std::path::Path;

use crate::error::{io, Result, ViewerError};
use crate::outdir::OutDir;

/// The page: name → bytes. `viewer.js` and the licence file are built by `web/build.sh`.
pub const ASSETS: [(&str, &[u8]); 3] = [
    ("index.html", include_bytes!("../assets/index.html")),
    ("viewer.js", include_bytes!("../assets/viewer.js")),
    ("THIRD_PARTY_LICENSES.txt", include_bytes!("../assets/THIRD_PARTY_LICENSES.txt")),
];

/// A page asset by name (the name returned is the static one).
pub fn asset(name: &str) -> Option<(&'static str, &'static [u8])> {
    ASSETS.iter().find(|(n, _)| *n == name).copied()
}

/// Write the page for `out` into `dest` as a self-contained folder (page, bundle, manifest, and a copy of the
/// render's files under `data/`) that any static web host can serve. `dest` must be missing, empty or an
/// earlier export.
pub fn write_static(out: &OutDir, dest: &Path) -> Result<()> {
    if dest.exists() {
        let empty = std::fs::read_dir(dest).map_err(io(dest))?.next().is_none();
        if !empty && !dest.join("manifest.json").is_file() {
            return Err(ViewerError::StaticDest {
                path: dest.to_path_buf(),
                msg: "exists and is not empty (nor an earlier `view --static` export); pick a new folder".into(),
            });
        }
    }
    std::fs::create_dir_all(dest).map_err(io(dest))?;
    if dest.canonicalize().map_err(io(dest))?.starts_with(&out.root) {
        return Err(ViewerError::StaticDest { path: dest.to_path_buf(), msg: "is inside the render folder; pick another folder".into() });
    }
    // An earlier export's frames may be stale (the render was redone): start the data over.
    let old = dest.join("data");
    if old.exists() {
        std::fs::remove_dir_all(&old).map_err(io(&old))?;
    }
    let manifest = out.manifest();
    for rel in manifest.paths() {
        // A link to a file outside the render folder would publish it: refuse, naming it.
        let from = out.root.join(&rel);
        let real = from.canonicalize().map_err(io(&from))?;
        if !real.starts_with(&out.root) {
            return Err(ViewerError::StaticDest {
                path: from,
                msg: format!("is a link to {}, outside the render folder; copy the file in, or remove the link", real.display()),
            });
        }
        let to = dest.join("data").join(&rel);
        if let Some(parent) = to.parent() {
            std::fs::create_dir_all(parent).map_err(io(parent))?;
        }
        std::fs::copy(out.root.join(&rel), &to).map_err(io(&to))?;
    }
    for (name, bytes) in ASSETS {
        std::fs::write(dest.join(name), bytes).map_err(io(dest.join(name)))?;
    }
    let json = serde_json::to_vec_pretty(&manifest).map_err(|e| ViewerError::StaticDest { path: dest.to_path_buf(), msg: e.to_string() })?;
    // Written last: a folder with a manifest is a complete export.
    std::fs::write(dest.join("manifest.json"), json).map_err(io(dest.join("manifest.json")))
}
