//! Names of weights and data: `hf:OWNER/REPO[/PATH][@REV]`, the Hub's `…/resolve/REV/PATH` URL, or a short name.

use crate::error::{Error, Result};

/// The branch a name without `@REV` means.
pub const DEFAULT_REVISION: &str = "main";

/// A file (or, without `path`, the whole repository as a folder) of a model repository on the Hub.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HubFile {
    /// `OWNER/REPO`.
    pub repo: String,
    /// A branch, tag or commit hash (`main` unless given).
    pub revision: String,
    /// The file's path inside the repository; `None`: every file of the repository.
    pub path: Option<String>,
}

impl HubFile {
    /// The `hf:` spelling of this address.
    pub fn address(&self) -> String {
        let mut s = format!("hf:{}", self.repo);
        if let Some(p) = &self.path {
            s.push('/');
            s.push_str(p);
        }
        if self.revision != DEFAULT_REVISION {
            s.push('@');
            s.push_str(&self.revision);
        }
        s
    }

    /// What the file is called in messages: `PATH of OWNER/REPO at revision REV`.
    pub fn describe(&self) -> String {
        match &self.path {
            Some(p) => format!("{p} of {} at revision {}", self.repo, self.revision),
            None => format!("the repository {} at revision {}", self.repo, self.revision),
        }
    }
}

/// What a name stands for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Name {
    /// `default`: the model shipped with the project (`assets/models/default`); nothing to fetch.
    ShippedDefault,
    /// A file or repository on the Hub.
    Hub(HubFile),
}

/// One entry of the short-name table.
#[derive(Debug, Clone, Copy)]
pub struct ShortName {
    /// The short name (`dl3dv`, `vggt-1b`, …).
    pub name: &'static str,
    /// Its `hf:` address; empty for `default`.
    pub address: &'static str,
    /// What it is.
    pub what: &'static str,
    /// Its licence, as its repository states it.
    pub licence: &'static str,
    /// Whether the repository is gated (access requested on its page, then `HF_TOKEN`).
    pub gated: bool,
    /// What to know before using it.
    pub note: &'static str,
}

/// The short names, in the order `weights list` shows them.
pub const SHORT_NAMES: &[ShortName] = &[
    ShortName {
        name: "default",
        address: "",
        what: "the model shipped with this project (assets/models/default)",
        licence: "MIT (this project)",
        gated: false,
        note: "nothing to fetch; trained on synthetic POV-Ray and procedural scenes (assets/models/default/MODEL.md)",
    },
    ShortName {
        name: "dl3dv",
        address: "hf:donydchen/mvsplat360/dl3dv_480p.ckpt",
        what: "the official MVSplat360 checkpoint (encoder + refiner), DL3DV, 480p",
        licence: "MIT (the MVSplat360 code); trained on DL3DV-10K, whose terms allow non-commercial research only",
        gated: false,
        note: "needs SVD-sized memory for the refiner; converted to safetensors once into $MVSPLAT360_CACHE",
    },
    ShortName {
        name: "dl3dv-tiny",
        address: "hf:donydchen/mvsplat360/dl3dv_tiny.zip",
        what: "5 pre-processed DL3DV test scenes (.torch chunks) for a quick official-protocol evaluation",
        licence: "DL3DV-10K terms of use (non-commercial research)",
        gated: false,
        note: "a zip, unpacked once into $MVSPLAT360_CACHE keyed by its SHA-256",
    },
    ShortName {
        name: "vggt-1b",
        address: "hf:facebook/VGGT-1B/model.pt",
        what: "VGGT 1B weights for the VGGT pose engine",
        licence: "CC BY-NC 4.0 (non-commercial)",
        gated: false,
        note: "for commercial use take vggt-1b-commercial",
    },
    ShortName {
        name: "vggt-1b-commercial",
        address: "hf:facebook/VGGT-1B-Commercial/model.pt",
        what: "VGGT 1B weights under Meta's licence that allows commercial use",
        licence: "VGGT licence (Meta), accepted on the repository page",
        gated: true,
        note: "gated: request access at https://huggingface.co/facebook/VGGT-1B-Commercial, then set HF_TOKEN",
    },
    ShortName {
        name: "svd",
        address: "hf:stabilityai/stable-video-diffusion-img2vid/svd.safetensors",
        what: "Stable Video Diffusion (img2vid), the refiner's initialisation for training",
        licence: "Stability AI's licence for SVD, accepted on the repository page",
        gated: true,
        note: "gated: request access at https://huggingface.co/stabilityai/stable-video-diffusion-img2vid, then set HF_TOKEN",
    },
];

/// The short-name entry called `name`.
pub fn short_name(name: &str) -> Option<&'static ShortName> {
    SHORT_NAMES.iter().find(|s| s.name == name)
}

/// Parses a name: a short name, `hf:OWNER/REPO[/PATH][@REV]`, or a resolve URL of `endpoint` (or of
/// https://huggingface.co). Does not look at the file system: the caller checks for an existing path first.
pub fn parse(spec: &str, endpoint: &str) -> Result<Name> {
    if let Some(s) = short_name(spec) {
        return if s.address.is_empty() { Ok(Name::ShippedDefault) } else { parse(s.address, endpoint) };
    }
    if let Some(rest) = spec.strip_prefix("hf:") {
        return parse_hf(rest, spec).map(Name::Hub);
    }
    for origin in [endpoint.trim_end_matches('/'), crate::DEFAULT_ENDPOINT] {
        if let Some(rest) = spec.strip_prefix(origin).and_then(|r| r.strip_prefix('/')) {
            return parse_url(rest, spec).map(Name::Hub);
        }
    }
    Err(Error::BadName(bad_name(spec)))
}

fn bad_name(spec: &str) -> String {
    let names: Vec<&str> = SHORT_NAMES.iter().map(|s| s.name).collect();
    format!(
        "{spec:?} is neither an existing file or folder nor a name: give a path, a short name ({}), \
         hf:OWNER/REPO[/PATH][@REVISION] or a Hub URL https://huggingface.co/OWNER/REPO/resolve/REVISION/PATH",
        names.join(", ")
    )
}

fn parse_hf(rest: &str, spec: &str) -> Result<HubFile> {
    let bad = |why: &str| Error::BadName(format!("{spec:?}: {why}; the form is hf:OWNER/REPO[/PATH][@REVISION]"));
    let (owner, after) = rest.split_once('/').ok_or_else(|| bad("no repository after the owner"))?;
    // The repository ends at the first '/' or '@'; `@REV` right after it may hold '/' (refs/pr/1), after a path
    // the revision follows the last '@'.
    let end = after.find(['/', '@']).unwrap_or(after.len());
    let (repo, tail) = after.split_at(end);
    let (path, revision) = if let Some(rev) = tail.strip_prefix('@') {
        (None, Some(rev))
    } else if let Some(t) = tail.strip_prefix('/') {
        match t.rsplit_once('@') {
            Some((p, r)) => (Some(p), Some(r)),
            None => (Some(t), None),
        }
    } else {
        (None, None)
    };
    check_part(owner, "owner").map_err(|w| bad(&w))?;
    check_part(repo, "repository").map_err(|w| bad(&w))?;
    let path = match path {
        Some(p) => Some(check_path(p.trim_end_matches('/')).map_err(|w| bad(&w))?),
        None => None,
    };
    let revision = match revision {
        Some("") => return Err(bad("an empty revision after '@'")),
        Some(r) => r.to_string(),
        None => DEFAULT_REVISION.to_string(),
    };
    check_revision(&revision).map_err(|w| bad(&w))?;
    Ok(HubFile { repo: format!("{owner}/{repo}"), revision, path: path.filter(|p| !p.is_empty()) })
}

fn parse_url(rest: &str, spec: &str) -> Result<HubFile> {
    let bad = || Error::BadName(format!("{spec:?} is not a Hub file URL: the form is https://huggingface.co/OWNER/REPO/resolve/REVISION/PATH"));
    let rest = rest.split(['?', '#']).next().unwrap_or("");
    let parts: Vec<&str> = rest.splitn(5, '/').collect();
    if parts.len() != 5 || (parts[2] != "resolve" && parts[2] != "blob") {
        return Err(bad());
    }
    let (owner, repo, revision, path) = (parts[0], parts[1], percent_decode(parts[3]), percent_decode(parts[4]));
    check_part(owner, "owner").map_err(|_| bad())?;
    check_part(repo, "repository").map_err(|_| bad())?;
    check_revision(&revision).map_err(|_| bad())?;
    let path = check_path(&path).map_err(|_| bad())?;
    Ok(HubFile { repo: format!("{owner}/{repo}"), revision, path: Some(path) })
}

fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' && i + 2 < b.len() {
            if let (Some(h), Some(l)) = ((b[i + 1] as char).to_digit(16), (b[i + 2] as char).to_digit(16)) {
                out.push((h * 16 + l) as u8);
                i += 3;
                continue;
            }
        }
        out.push(b[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

fn check_part(s: &str, what: &str) -> std::result::Result<(), String> {
    let ok = !s.is_empty()
        && s.len() <= 96
        && s.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
        && !s.starts_with(['-', '.'])
        && !s.contains("--")
        && !s.contains("..");
    if ok {
        Ok(())
    } else {
        Err(format!("{s:?} is not a valid {what} name (letters, digits, '-', '_', '.')"))
    }
}

/// A file path inside a repository: relative, no `..`, no empty or `.` components.
pub(crate) fn check_path(p: &str) -> std::result::Result<String, String> {
    if p.is_empty() {
        return Ok(String::new());
    }
    if p.starts_with('/') || p.contains('\\') || p.split('/').any(|c| c.is_empty() || c == "." || c == "..") {
        return Err(format!("{p:?} is not a relative path inside the repository"));
    }
    Ok(p.to_string())
}

fn check_revision(r: &str) -> std::result::Result<(), String> {
    if r.is_empty() || r.starts_with('/') || r.split('/').any(|c| c.is_empty() || c == "." || c == "..") || r.contains('\\') {
        return Err(format!("{r:?} is not a valid revision"));
    }
    Ok(())
}

/// Whether `s` is a full commit hash (40 lowercase hex digits), as Python's `REGEX_COMMIT_HASH`.
pub fn is_commit_hash(s: &str) -> bool {
    s.len() == 40 && s.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hub(spec: &str) -> HubFile {
        match parse(spec, "http://127.0.0.1:9").unwrap() {
            Name::Hub(f) => f,
            n => panic!("{n:?}"),
        }
    }

    #[test]
    fn hf_names() {
        assert_eq!(hub("hf:a/b"), HubFile { repo: "a/b".into(), revision: "main".into(), path: None });
        assert_eq!(hub("hf:a/b@v1"), HubFile { repo: "a/b".into(), revision: "v1".into(), path: None });
        assert_eq!(hub("hf:a/b/c/d.pt"), HubFile { repo: "a/b".into(), revision: "main".into(), path: Some("c/d.pt".into()) });
        assert_eq!(hub("hf:a/b/c/d.pt@dev"), HubFile { repo: "a/b".into(), revision: "dev".into(), path: Some("c/d.pt".into()) });
        assert_eq!(hub("hf:a/b@refs/pr/1"), HubFile { repo: "a/b".into(), revision: "refs/pr/1".into(), path: None });
        assert_eq!(hub("dl3dv").address(), "hf:donydchen/mvsplat360/dl3dv_480p.ckpt");
        assert_eq!(parse("default", "x").unwrap(), Name::ShippedDefault);
        for bad in ["hf:a", "hf:a/../x", "hf:a/b/../c", "hf:a/b/c@", "hf:/b/c", "model.pt", "hf:a/b//c"] {
            assert!(parse(bad, "x").is_err(), "{bad}");
        }
    }

    #[test]
    fn urls() {
        let f = hub("https://huggingface.co/facebook/VGGT-1B/resolve/main/model.pt?download=true");
        assert_eq!(f, HubFile { repo: "facebook/VGGT-1B".into(), revision: "main".into(), path: Some("model.pt".into()) });
        let f = hub("http://127.0.0.1:9/o/r/resolve/refs%2Fpr%2F2/a/b.bin");
        assert_eq!(f, HubFile { repo: "o/r".into(), revision: "refs/pr/2".into(), path: Some("a/b.bin".into()) });
        assert!(parse("https://example.com/o/r/resolve/main/x", "http://127.0.0.1:9").is_err());
        assert!(parse("https://huggingface.co/o/r/tree/main/x", "x").is_err());
    }

    #[test]
    fn every_short_name_parses() {
        for s in SHORT_NAMES {
            parse(s.name, "x").unwrap();
        }
    }
}
