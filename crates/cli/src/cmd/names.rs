//! Weights and data by name for every flag that takes them (`--ckpt`, `--encoder`, `--refiner`, `--vggt-weights`,
//! `eval --data`, `train`'s `init` and `refiner_init`): an existing path as given; else `default` (the shipped
//! model folder), a short name (`dl3dv`, `vggt-1b`, … — `mvsplat360 weights list`), `hf:OWNER/REPO[/PATH][@REV]`
//! or a Hub `…/resolve/REV/PATH` URL, fetched into the Hugging Face cache by `mvsplat360_hub` with a download bar.
//! Names are resolved here, before any request to the pipeline is built; the pipeline only sees paths.

use std::path::{Path, PathBuf};

use anyhow::Context;
use mvsplat360_hub::{Hub, Resolved};

/// What `default` stands for at a flag.
#[derive(Clone, Copy)]
pub enum Default {
    /// The shipped model folder (`assets/models/default`): `--ckpt`, `train.init`, model folders.
    ModelFolder,
    /// Nothing this flag takes; the text says what to give instead.
    Refuse(&'static str),
}

/// Whether the Hub is asked about a name that is cached already.
#[derive(Clone, Copy, PartialEq, Eq)]
pub enum Freshness {
    /// As the Python client: ask the Hub which commit the revision is at (one HEAD request), download if it moved.
    Ask,
    /// The cached file if there is one, without a request: the file a run started with (a `train --resume`,
    /// `--export`, the ranks a command started after fetching it). A whole repository (`hf:OWNER/REPO`) is asked
    /// for as with `Ask`.
    CachedFirst,
}

/// `spec` resolved for `flag`: the path itself when it exists, else the name's file or folder.
pub fn resolve(spec: &Path, flag: &str, default: Default, fresh: Freshness, quiet: bool) -> anyhow::Result<PathBuf> {
    if spec.exists() {
        return Ok(spec.to_path_buf());
    }
    // A path that is not UTF-8 is no name: left to the command, which says it does not exist.
    let Some(text) = spec.to_str() else { return Ok(spec.to_path_buf()) };
    let hub = Hub::from_env();
    // A file only: a repository's snapshot folder in the cache may hold some of its files (those fetched one by one).
    let one_file = matches!(hub.parse(text), Ok(mvsplat360_hub::Name::Hub(f)) if f.path.is_some());
    if fresh == Freshness::CachedFirst && one_file {
        if let Some(p) = hub.cached(text) {
            return Ok(p);
        }
    }
    let bar = super::progress::DownloadBar::new(quiet);
    let resolved = match hub.resolve(text, &bar) {
        Ok(r) => r,
        // A missing file spelled as a path (`weights/model.pt`, `svd.safetensors`) is the command's to report, in
        // its own words (what the flag takes, where to get it); a bare word (`dl3dvv`) or a malformed `hf:`/URL
        // name gets the list of names.
        Err(mvsplat360_hub::Error::BadName(_)) if looks_like_a_path(text) => return Ok(spec.to_path_buf()),
        Err(e) => anyhow::bail!("{flag} {text}: {e}"),
    };
    let path = match resolved {
        Resolved::Path(p) => p,
        Resolved::ShippedDefault => match default {
            Default::ModelFolder => mvsplat360_pipeline::model::default_model_dir()
                .context(format!("{flag} default: the shipped model assets/models/default is missing; run from a clone of the repository"))?,
            Default::Refuse(instead) => anyhow::bail!("{flag} default: `default` is the shipped model folder, not {instead}"),
        },
    };
    if !quiet {
        eprintln!("{flag} {text}: {}", path.display());
    }
    Ok(path)
}

/// Whether a text that is no name was meant as a path: it has a folder or an extension, and is no attempt at an
/// `hf:` name or a URL.
fn looks_like_a_path(text: &str) -> bool {
    !text.starts_with("hf:") && !text.contains("://") && (text.contains(std::path::MAIN_SEPARATOR) || text.contains('/') || text.contains('.'))
}

/// [`resolve`] of an optional flag, in place.
pub fn resolve_opt(spec: &mut Option<PathBuf>, flag: &str, default: Default, fresh: Freshness, quiet: bool) -> anyhow::Result<()> {
    if let Some(s) = spec.as_ref() {
        *spec = Some(resolve(s, flag, default, fresh, quiet)?);
    }
    Ok(())
}

/// Data given to `eval --data`: a folder as it is; a `.zip` (local, or a name's file such as `dl3dv-tiny`) unpacked
/// once into `$MVSPLAT360_CACHE/data/<its SHA-256>`; a name of a whole repository: its snapshot folder. Returns the
/// folder and whether it came from a zip.
pub fn data(spec: &Path, fresh: Freshness, quiet: bool) -> anyhow::Result<(PathBuf, bool)> {
    let p = resolve(spec, "--data", Default::Refuse("data (give a folder of .torch chunks, a .zip of them, or dl3dv-tiny)"), fresh, quiet)?;
    if p.is_dir() || !p.exists() {
        // A missing folder is reported by `eval` with the flag's usual message.
        return Ok((p, false));
    }
    let root = mvsplat360_pipeline::model::cache_dir().join("data");
    let dir = mvsplat360_hub::unpack_zip(&p, &root).map_err(|e| anyhow::anyhow!("--data {}: {e}", spec.display()))?;
    if !quiet {
        eprintln!("--data {}: unpacked into {}", p.display(), dir.display());
    }
    Ok((dir, true))
}

/// The folder of `.torch` chunks under `root`: `root` itself when it holds chunks, its `test/` split, or the
/// end of a chain of single folders leading to either (as a zip with one top-level folder unpacks). Returns
/// the folder and, when it is not `root`, why it was taken.
pub fn chunk_folder(root: &Path) -> anyhow::Result<(PathBuf, Option<String>)> {
    let has_chunks =
        |d: &Path| std::fs::read_dir(d).is_ok_and(|rd| rd.flatten().any(|e| e.path().is_file() && e.file_name().to_string_lossy().ends_with(".torch")));
    let mut dir = root.to_path_buf();
    for _ in 0..8 {
        if has_chunks(&dir) {
            let why = (dir != root).then(|| format!("the only folder with chunks in {}", root.display()));
            return Ok((dir, why));
        }
        if has_chunks(&dir.join("test")) {
            return Ok((dir.join("test"), Some("the test split".to_string())));
        }
        let subs: Vec<PathBuf> = std::fs::read_dir(&dir)
            .map(|rd| {
                rd.flatten()
                    .filter(|e| e.path().is_dir())
                    .filter(|e| {
                        let n = e.file_name().to_string_lossy().into_owned();
                        !n.starts_with('.') && n != "__MACOSX"
                    })
                    .map(|e| e.path())
                    .collect()
            })
            .unwrap_or_default();
        match subs.as_slice() {
            [one] => dir = one.clone(),
            _ => {
                let names: Vec<String> = subs.iter().filter_map(|s| s.file_name().map(|n| n.to_string_lossy().into_owned())).collect();
                anyhow::bail!(
                    "--data {}: no .torch chunks in {}, in its test/ folder or down a single chain of folders{}; give the folder holding the chunks",
                    root.display(),
                    dir.display(),
                    if names.is_empty() { String::new() } else { format!(" (it has the folders {})", names.join(", ")) }
                );
            }
        }
    }
    anyhow::bail!("--data {}: no .torch chunks within 8 levels of folders", root.display())
}
