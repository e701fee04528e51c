//! One file (or a repository's files) into the cache: metadata from the resolve endpoint, the blob written under
//! the `.locks` flock as `<etag>.incomplete` (resumed with `Range`), checked, renamed, linked from the snapshot.

use crate::cache::{not_cached_hint, remove_if_present, FileLock};
use crate::error::{io, Error, Result};
use crate::http::{error_code, join, Follow, Resp};
use crate::names::{is_commit_hash, HubFile};
use crate::{Hub, Progress};
use sha2::Digest;
use std::io::{Read, Seek, Write};
use std::path::{Path, PathBuf};

/// What the resolve endpoint says about a file.
struct Meta {
    commit: String,
    etag: String,
    size: Option<u64>,
    url: String,
    check: Check,
}

/// The checksum the Hub announces for a file.
#[derive(Debug, Clone)]
enum Check {
    /// An LFS file: the SHA-256 of its content (`X-Linked-Etag`).
    Sha256(String),
    /// A file stored in git: its blob id, SHA-1 of `blob {len}\0` + content (`ETag`).
    GitSha1(String),
    /// Neither: the size alone is checked.
    None,
}

/// `_normalize_etag`: without a leading `W/` and the quotes.
fn normalize_etag(e: &str) -> String {
    e.trim().trim_start_matches("W/").trim_matches('"').to_string()
}

fn is_hex(s: &str, len: usize) -> bool {
    s.len() == len && s.bytes().all(|b| b.is_ascii_hexdigit())
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// The revision as a URL path segment (`refs/pr/1` → `refs%2Fpr%2F1`, as Python's `quote(revision, safe="")`).
fn quote(s: &str) -> String {
    let mut out = String::new();
    for b in s.bytes() {
        if b.is_ascii_alphanumeric() || matches!(b, b'-' | b'_' | b'.' | b'~') {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

/// A file path as URL path segments.
fn quote_path(p: &str) -> String {
    p.split('/').map(quote).collect::<Vec<_>>().join("/")
}

impl Hub {
    fn resolve_url(&self, repo: &str, revision: &str, path: &str) -> String {
        format!("{}/{repo}/resolve/{}/{}", self.http.endpoint(), quote(revision), quote_path(path))
    }

    /// The page where a repository is shown (and gated access requested).
    fn page(&self, repo: &str) -> String {
        format!("{}/{repo}", self.http.endpoint())
    }

    pub(crate) fn fetch_file(&self, repo: &str, revision: &str, path: &str, progress: &dyn Progress) -> Result<PathBuf> {
        let file = HubFile { repo: repo.to_string(), revision: revision.to_string(), path: Some(path.to_string()) };
        if is_commit_hash(revision) {
            let p = self.cache.pointer(repo, revision, path);
            if p.exists() {
                return Ok(p);
            }
        }
        if self.config.offline {
            return self.cache.cached(&file).ok_or_else(|| self.offline_error(&file));
        }
        let url = self.resolve_url(repo, revision, path);
        let r = match self.http.request(false, &url, None, Follow::SameOrigin) {
            Ok(r) if r.status >= 500 || r.status == 429 => return self.unreachable(&file, &format!("it answered {}", r.status), progress),
            Ok(r) => r,
            Err(e) => return self.unreachable(&file, &e.to_string(), progress),
        };
        if r.status >= 400 {
            return Err(self.http_error(&r, &file));
        }
        let meta = self.meta(&r, &file)?;
        let pointer = self.cache.pointer(repo, &meta.commit, path);
        if pointer.exists() {
            self.cache.write_ref(repo, revision, &meta.commit)?;
            return Ok(pointer);
        }
        self.cache.write_ref(repo, revision, &meta.commit)?;
        let blob = self.cache.blob(repo, &meta.etag);
        let lock_path = self.cache.lock_path(repo, &meta.etag);
        let _lock =
            FileLock::acquire(&lock_path, || progress.note(&format!("waiting for another download of {} (lock {})", file.describe(), lock_path.display())))?;
        if !blob.exists() {
            self.download(&meta, &file, &blob, progress)?;
        }
        self.cache.link(repo, &meta.commit, path, &meta.etag)
    }

    pub(crate) fn fetch_repo(&self, repo: &str, revision: &str, progress: &dyn Progress) -> Result<PathBuf> {
        let file = HubFile { repo: repo.to_string(), revision: revision.to_string(), path: None };
        if self.config.offline {
            return self.cache.cached(&file).ok_or_else(|| self.offline_error(&file));
        }
        let url = format!("{}/api/models/{repo}/revision/{}", self.http.endpoint(), quote(revision));
        let (r, json) = match self.http.get_json(&url) {
            Ok((r, _)) if r.status >= 500 || r.status == 429 => {
                return self.unreachable(&file, &format!("it answered {}", r.status), progress);
            }
            Ok(x) => x,
            Err(e) => return self.unreachable(&file, &e.to_string(), progress),
        };
        if r.status != 200 {
            return Err(self.http_error(&r, &file));
        }
        let bad = || Error::Http(format!("the Hub's file list of {} ({url}) is not the JSON expected (sha, siblings[].rfilename)", file.describe()));
        let json = json.ok_or_else(bad)?;
        let commit = json.get("sha").and_then(|s| s.as_str()).filter(|s| is_commit_hash(s)).ok_or_else(bad)?.to_string();
        let siblings = json.get("siblings").and_then(|s| s.as_array()).ok_or_else(bad)?;
        let mut paths = Vec::new();
        for s in siblings {
            let p = s.get("rfilename").and_then(|p| p.as_str()).ok_or_else(bad)?;
            let p = crate::names::check_path(p).map_err(|w| Error::Http(format!("the Hub lists a file of {repo} that is not a safe path: {w}")))?;
            paths.push(p);
        }
        for p in &paths {
            self.fetch_file(repo, &commit, p, progress)?;
        }
        self.cache.write_ref(repo, revision, &commit)?;
        let dir = self.cache.snapshot(repo, &commit);
        std::fs::create_dir_all(&dir).map_err(|e| io("cannot create", &dir, e))?;
        Ok(dir)
    }

    /// The Hub could not be reached (or failed): the cached copy of that revision with a note, else an error.
    fn unreachable(&self, file: &HubFile, why: &str, progress: &dyn Progress) -> Result<PathBuf> {
        if let Some(p) = self.cache.cached(file) {
            let commit = self.cache.commit_of(&file.repo, &file.revision).unwrap_or_default();
            progress.note(&format!(
                "the Hub ({}) could not be reached ({why}); using the cached {} (commit {commit}), which may be older than the Hub's",
                self.http.endpoint(),
                file.describe()
            ));
            return Ok(p);
        }
        Err(Error::Unreachable(format!(
            "cannot reach the Hub at {} ({why}) and {} is not in the cache {}: check the network (or HF_ENDPOINT), \
             or download it where the Hub is reachable and copy the cache folder {} here, or give a local path instead of the name",
            self.http.endpoint(),
            file.describe(),
            self.cache.root().display(),
            crate::Cache::repo_folder(&file.repo),
        )))
    }

    fn offline_error(&self, file: &HubFile) -> Error {
        Error::Offline(format!(
            "HF_HUB_OFFLINE is set and {} is not in the cache {}: unset HF_HUB_OFFLINE to download it; or, on a machine \
             with access, download it (this program, or Python's `hf download {}{}`) and copy the cache folder {} here; \
             or {}; or give a local path instead of the name",
            file.describe(),
            self.cache.root().display(),
            file.repo,
            file.path.as_deref().map(|p| format!(" {p}")).unwrap_or_default(),
            crate::Cache::repo_folder(&file.repo),
            not_cached_hint(&self.cache, file),
        ))
    }

    /// An error answer to the metadata request, by status and `X-Error-Code` (Python's `hf_raise_for_status`).
    fn http_error(&self, r: &Resp, file: &HubFile) -> Error {
        let page = self.page(&file.repo);
        let message = r.header("x-error-message").unwrap_or("");
        let code = error_code(r);
        let token = self.config.token.as_deref();
        let token_from = if token.is_some() && std::env::var("HF_TOKEN").ok().as_deref().map(str::trim) == token {
            "HF_TOKEN".to_string()
        } else if token.is_some() && std::fs::read_to_string(&self.config.token_path).ok().as_deref().map(str::trim) == token {
            format!("the token file {}", self.config.token_path.display())
        } else {
            "the token given to this program".to_string()
        };
        let set_token =
            format!("then set HF_TOKEN to a token of that account (https://huggingface.co/settings/tokens), or put it in {}", self.config.token_path.display());
        match (r.status, code) {
            (403, Some("GatedRepo")) if self.http.has_token() => Error::Gated(format!(
                "{} is a gated repository and the token in use ({token_from}) belongs to an account without access to it yet: \
                 request access at {page} with that account (access may need the authors' approval), or use a token of an account that has it",
                file.repo
            )),
            (_, Some("GatedRepo")) => Error::Gated(format!(
                "{} is a gated repository: request access at {page} (logged in to your account, accepting its licence), {set_token}",
                file.repo
            )),
            (401, _) if message.contains("Invalid credentials") || message.contains("Invalid username or password") => Error::BadToken(format!(
                "the Hub rejected the token in use ({token_from}): it is expired, revoked or mistyped; create a new one at \
                 https://huggingface.co/settings/tokens and set HF_TOKEN to it"
            )),
            (_, Some("RepoNotFound")) | (401, None) => Error::NotFound(format!(
                "repository {} not found on {}: check OWNER/REPO in {}; if it is private, {}",
                file.repo,
                self.http.endpoint(),
                file.address(),
                if self.http.has_token() {
                    format!("the token in use ({token_from}) has no access to it")
                } else {
                    format!("it needs a token: {}", set_token.trim_start_matches("then "))
                }
            )),
            (_, Some("RevisionNotFound")) => Error::NotFound(format!(
                "revision {:?} not found in {}: check @{} in {}; it must be a branch, tag or commit of the repository (branches and tags: {page}/tree/main)",
                file.revision,
                file.repo,
                file.revision,
                file.address()
            )),
            (_, Some("EntryNotFound")) | (404, _) => Error::NotFound(format!(
                "{} not found: the repository {} and revision {} exist but have no such file; check the path in {} (its files: {page}/tree/{})",
                file.path.as_deref().unwrap_or("the file"),
                file.repo,
                file.revision,
                file.address(),
                quote(&file.revision),
            )),
            (status, _) => Error::Http(format!(
                "the Hub answered {status}{} for {}{}",
                code.map(|c| format!(" ({c})")).unwrap_or_default(),
                file.describe(),
                if message.is_empty() { String::new() } else { format!(": {message}") }
            )),
        }
    }

    /// The metadata of a successful (2xx or cross-origin redirect) answer to the HEAD request.
    fn meta(&self, r: &Resp, file: &HubFile) -> Result<Meta> {
        let missing = |h: &str| {
            Error::Http(format!(
                "the answer for {} has no {h} header ({}): is {} a Hugging Face Hub (HF_ENDPOINT)?",
                file.describe(),
                r.url,
                self.http.endpoint()
            ))
        };
        let commit = r.header("x-repo-commit").map(str::trim).filter(|c| !c.is_empty()).ok_or_else(|| missing("X-Repo-Commit"))?.to_string();
        let linked = r.header("x-linked-etag").map(normalize_etag);
        let etag = linked.clone().or_else(|| r.header("etag").map(normalize_etag)).filter(|e| !e.is_empty()).ok_or_else(|| missing("ETag"))?;
        let unsafe_name = |n: &str| n.contains(['/', '\\', '\0']) || n.starts_with('.');
        if unsafe_name(&etag) || unsafe_name(&commit) {
            return Err(Error::Http(format!("the Hub's answer for {} has an unusable ETag {etag:?} or commit {commit:?}", file.describe())));
        }
        let size =
            r.header("x-linked-size").or_else(|| if r.is_redirect() { None } else { r.header("content-length") }).and_then(|s| s.trim().parse::<u64>().ok());
        let url = if r.is_redirect() { r.header("location").map(|l| join(&r.url, l)).unwrap_or_else(|| r.url.clone()) } else { r.url.clone() };
        let check = match &linked {
            Some(e) if is_hex(e, 64) => Check::Sha256(e.to_ascii_lowercase()),
            None if is_hex(&etag, 40) => Check::GitSha1(etag.to_ascii_lowercase()),
            _ => Check::None,
        };
        Ok(Meta { commit, etag, size, url, check })
    }

    /// Downloads `meta.url` into `blob` via `<etag>.incomplete` (resumed if present); called under the lock.
    fn download(&self, meta: &Meta, file: &HubFile, blob: &Path, progress: &dyn Progress) -> Result<()> {
        let name = file.path.as_deref().unwrap_or("file");
        let part = self.cache.incomplete(&file.repo, &meta.etag);
        let dir = part.parent().expect("blobs folder");
        std::fs::create_dir_all(dir).map_err(|e| io("cannot create", dir, e))?;
        adopt_python_partial(&part, &meta.etag)?;
        let mut f = std::fs::OpenOptions::new().create(true).read(true).append(true).open(&part).map_err(|e| io("cannot open", &part, e))?;
        let mut kept = f.metadata().map_err(|e| io("cannot read", &part, e))?.len();
        if meta.size.is_some_and(|s| kept > s) {
            f.set_len(0).map_err(|e| io("cannot truncate", &part, e))?;
            kept = 0;
        }
        let mut sha = sha2::Sha256::new();
        if kept > 0 && matches!(meta.check, Check::Sha256(_)) {
            f.seek(std::io::SeekFrom::Start(0)).map_err(|e| io("cannot read", &part, e))?;
            hash_reader(&mut (&f).take(kept), &mut sha).map_err(|e| io("cannot read", &part, e))?;
        }
        let total = if meta.size == Some(kept) {
            progress.start(name, meta.size, kept);
            kept
        } else {
            let mut r = self.get(&meta.url, kept, file)?;
            if kept > 0 && r.status == 200 {
                // The server ignored the Range: start over.
                f.set_len(0).map_err(|e| io("cannot truncate", &part, e))?;
                kept = 0;
                sha = sha2::Sha256::new();
            } else if r.status == 416 {
                f.set_len(0).map_err(|e| io("cannot truncate", &part, e))?;
                kept = 0;
                sha = sha2::Sha256::new();
                r = self.get(&meta.url, 0, file)?;
            }
            if r.status == 206 {
                let start = r
                    .header("content-range")
                    .and_then(|c| c.trim().strip_prefix("bytes "))
                    .and_then(|c| c.split('-').next())
                    .and_then(|s| s.parse::<u64>().ok());
                if start != Some(kept) {
                    return Err(Error::Http(format!("asked for {} from byte {kept}, the server sent a part starting at {start:?}", file.describe())));
                }
            } else if r.status != 200 {
                return Err(Error::Http(format!(
                    "downloading {} from {} failed: the server answered {}; run again (a resume keeps the {kept} bytes already in {})",
                    file.describe(),
                    r.url,
                    r.status,
                    part.display()
                )));
            }
            let total = meta.size.or_else(|| r.header("content-length").and_then(|c| c.trim().parse::<u64>().ok()).map(|c| c + kept));
            progress.start(name, total, kept);
            let mut body = r.body.take().expect("GET has a body").into_reader();
            let mut buf = vec![0u8; 1 << 18];
            let mut got = kept;
            loop {
                let n = match body.read(&mut buf) {
                    Ok(0) => break,
                    Ok(n) => n,
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                    Err(e) => {
                        f.flush().map_err(|e| io("cannot write", &part, e))?;
                        return Err(interrupted(file, got, total, &part, &e.to_string()));
                    }
                };
                if total.is_some_and(|t| got + n as u64 > t) {
                    drop(f);
                    remove_if_present(&part)?;
                    return Err(Error::Corrupt(format!(
                        "{} is longer than the {} bytes the Hub announced; the partial file {} was deleted: run again",
                        file.describe(),
                        total.unwrap_or(0),
                        part.display()
                    )));
                }
                f.write_all(&buf[..n]).map_err(|e| io("cannot write", &part, e))?;
                if matches!(meta.check, Check::Sha256(_)) {
                    sha.update(&buf[..n]);
                }
                got += n as u64;
                progress.advance(n as u64);
            }
            f.flush().map_err(|e| io("cannot write", &part, e))?;
            match total {
                Some(t) if got < t => return Err(interrupted(file, got, total, &part, "the connection closed early")),
                _ => got,
            }
        };
        drop(f);
        let actual = match &meta.check {
            Check::Sha256(_) => Some(hex(&sha.finalize())),
            Check::GitSha1(_) => Some(git_blob_id(&part, total)?),
            Check::None => None,
        };
        match (&meta.check, actual) {
            (Check::Sha256(want), Some(got)) | (Check::GitSha1(want), Some(got)) if *want != got => {
                remove_if_present(&part)?;
                let what = if matches!(meta.check, Check::Sha256(_)) { "SHA-256 (X-Linked-Etag)" } else { "git blob id (ETag)" };
                return Err(Error::Corrupt(format!(
                    "{} arrived corrupt: its {what} is {got}, the Hub announced {want}; the partial file {} was deleted and \
                     nothing was cached. Run again; if it repeats, whatever serves {} (HF_ENDPOINT, a proxy) alters the file",
                    file.describe(),
                    part.display(),
                    meta.url
                )));
            }
            (Check::None, _) => progress.note(&format!("{}: the Hub gave no checksum (ETag {}); only its size was checked", file.describe(), meta.etag)),
            _ => {}
        }
        std::fs::rename(&part, blob).map_err(|e| io("cannot move the download to", blob, e))?;
        progress.finish(name);
        Ok(())
    }

    fn get(&self, url: &str, from: u64, file: &HubFile) -> Result<Resp> {
        self.http.request(true, url, (from > 0).then_some(from), Follow::All).map_err(|e| {
            Error::Interrupted(format!(
                "downloading {} from {url} failed ({e}); run again{}",
                file.describe(),
                if from > 0 { format!(" to resume from byte {from}") } else { String::new() }
            ))
        })
    }
}

fn interrupted(file: &HubFile, got: u64, total: Option<u64>, part: &Path, why: &str) -> Error {
    Error::Interrupted(format!(
        "the transfer of {} stopped after {got}{} bytes ({why}); the partial file {} is kept: run again to resume",
        file.describe(),
        total.map(|t| format!(" of {t}")).unwrap_or_default(),
        part.display()
    ))
}

fn hash_reader(r: &mut impl Read, h: &mut impl Digest) -> std::io::Result<u64> {
    let mut buf = vec![0u8; 1 << 18];
    let mut n = 0;
    loop {
        match r.read(&mut buf) {
            Ok(0) => return Ok(n),
            Ok(k) => {
                h.update(&buf[..k]);
                n += k as u64;
            }
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
}

/// SHA-1 of `blob {len}\0` + the file: its git blob id.
fn git_blob_id(path: &Path, len: u64) -> Result<String> {
    let mut h = sha1::Sha1::new();
    h.update(format!("blob {len}\0").as_bytes());
    let mut f = std::fs::File::open(path).map_err(|e| io("cannot read", path, e))?;
    hash_reader(&mut f, &mut h).map_err(|e| io("cannot read", path, e))?;
    Ok(hex(&h.finalize()))
}

/// Python 2.x writes `<etag>.<8 hex>.incomplete` and deletes it on failure — but a killed process leaves it. Under
/// the lock nobody writes one, so when `<etag>.incomplete` is absent the largest of them is taken over (the others
/// removed).
fn adopt_python_partial(part: &Path, etag: &str) -> Result<()> {
    if part.exists() {
        return Ok(());
    }
    let dir = part.parent().expect("blobs folder");
    let Ok(entries) = std::fs::read_dir(dir) else { return Ok(()) };
    let mut found: Vec<(u64, PathBuf)> = entries
        .filter_map(|e| e.ok())
        .filter(|e| {
            let n = e.file_name();
            let n = n.to_string_lossy();
            n.strip_prefix(etag)
                .and_then(|r| r.strip_prefix('.'))
                .and_then(|r| r.strip_suffix(".incomplete"))
                .is_some_and(|mid| mid.len() == 8 && mid.bytes().all(|b| b.is_ascii_hexdigit()))
        })
        .filter_map(|e| Some((e.metadata().ok()?.len(), e.path())))
        .collect();
    found.sort();
    if let Some((_, largest)) = found.pop() {
        std::fs::rename(&largest, part).map_err(|e| io("cannot take over the partial download", &largest, e))?;
        for (_, p) in found {
            remove_if_present(&p)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn etags() {
        assert_eq!(normalize_etag("W/\"abc\""), "abc");
        assert_eq!(normalize_etag("\"abc\""), "abc");
        assert_eq!(quote("refs/pr/1"), "refs%2Fpr%2F1");
        assert_eq!(quote_path("a b/c.pt"), "a%20b/c.pt");
    }
}
