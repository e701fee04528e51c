//! A Hugging Face Hub stand-in on 127.0.0.1: the resolve endpoint (HEAD/GET, `X-Repo-Commit`, `X-Linked-Etag`,
//! `X-Linked-Size`, `ETag`, `X-Error-Code`), the file-list API, LFS files redirected to a second port (the "CDN"),
//! `Range`, relative redirects; every request logged; faults on demand (a cut body, corrupt bytes, a held body).
//! Shared by the hub crate's tests and the CLI's (names in `render`, `eval`, `export`, `train`); point a client at it
//! with `HF_ENDPOINT` = [`StandIn::endpoint`].

use sha2::Digest;
use std::collections::HashMap;
use std::io::{BufRead, BufReader, Write};
use std::net::{TcpListener, TcpStream};
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

pub const COMMIT: &str = "0123456789abcdef0123456789abcdef01234567";

pub fn sha256_hex(b: &[u8]) -> String {
    sha2::Sha256::digest(b).iter().map(|x| format!("{x:02x}")).collect()
}

pub fn git_blob_id(b: &[u8]) -> String {
    let mut h = sha1::Sha1::new();
    h.update(format!("blob {}\0", b.len()).as_bytes());
    h.update(b);
    h.finalize().iter().map(|x| format!("{x:02x}")).collect()
}

/// Deterministic bytes.
pub fn bytes(n: usize, seed: u8) -> Vec<u8> {
    (0..n).map(|i| ((i as u32).wrapping_mul(2654435761) >> 13) as u8 ^ seed).collect()
}

#[derive(Clone)]
pub struct File {
    pub content: Vec<u8>,
    pub lfs: bool,
}

#[derive(Clone, Default)]
pub struct Repo {
    pub commit: String,
    pub files: Vec<(String, File)>,
    /// Tokens with access; `Some` makes the repository gated.
    pub gated: Option<Vec<String>>,
    /// Branches or tags besides `main` and the commit.
    pub revisions: Vec<String>,
}

#[derive(Debug, Clone)]
pub struct Req {
    pub cdn: bool,
    pub method: String,
    pub path: String,
    pub auth: Option<String>,
    pub range: Option<String>,
}

#[derive(Default)]
pub struct State {
    pub repos: HashMap<String, Repo>,
    /// `old/name` → `new/name`: a relative 307, as the Hub does for a renamed repository.
    pub aliases: HashMap<String, String>,
    pub log: Vec<Req>,
    /// The next body sent (hub or CDN) stops after this many bytes and the connection closes.
    pub cut_next_body_after: Option<usize>,
    /// Bodies are sent with one byte changed.
    pub corrupt: bool,
    /// A body of this path is held after half of it until this many HEAD requests for it arrived.
    pub hold: Option<(String, usize)>,
    /// `Range` is ignored: the whole body with 200, as some proxies do.
    pub ignore_range: bool,
}

pub struct StandIn {
    pub endpoint: String,
    pub cdn: String,
    pub state: Arc<Mutex<State>>,
}

impl StandIn {
    pub fn start() -> Self {
        let state = Arc::new(Mutex::new(State::default()));
        let hub = TcpListener::bind("127.0.0.1:0").unwrap();
        let cdn = TcpListener::bind("127.0.0.1:0").unwrap();
        let endpoint = format!("http://127.0.0.1:{}", hub.local_addr().unwrap().port());
        let cdn_url = format!("http://127.0.0.1:{}", cdn.local_addr().unwrap().port());
        for (listener, is_cdn) in [(hub, false), (cdn, true)] {
            let state = state.clone();
            let cdn_url = cdn_url.clone();
            std::thread::spawn(move || {
                for s in listener.incoming() {
                    let Ok(s) = s else { continue };
                    let state = state.clone();
                    let cdn_url = cdn_url.clone();
                    std::thread::spawn(move || {
                        let _ = serve(s, is_cdn, &state, &cdn_url);
                    });
                }
            });
        }
        Self { endpoint, cdn: cdn_url, state }
    }

    pub fn add_repo(&self, name: &str, repo: Repo) {
        self.state.lock().unwrap().repos.insert(name.to_string(), repo);
    }

    /// A repository `name` at [`COMMIT`] with these files.
    pub fn add(&self, name: &str, files: &[(&str, &[u8], bool)]) {
        let files = files.iter().map(|(p, c, lfs)| (p.to_string(), File { content: c.to_vec(), lfs: *lfs })).collect();
        self.add_repo(name, Repo { commit: COMMIT.into(), files, ..Default::default() });
    }

    pub fn log(&self) -> Vec<Req> {
        self.state.lock().unwrap().log.clone()
    }

    pub fn clear_log(&self) {
        self.state.lock().unwrap().log.clear();
    }

    pub fn gets(&self) -> Vec<Req> {
        self.log().into_iter().filter(|r| r.method == "GET").collect()
    }

    pub fn set(&self, f: impl FnOnce(&mut State)) {
        f(&mut self.state.lock().unwrap())
    }
}

fn serve(s: TcpStream, is_cdn: bool, state: &Mutex<State>, cdn: &str) -> std::io::Result<()> {
    s.set_read_timeout(Some(Duration::from_secs(30)))?;
    let mut r = BufReader::new(s.try_clone()?);
    let mut line = String::new();
    r.read_line(&mut line)?;
    let mut parts = line.split_whitespace();
    let method = parts.next().unwrap_or("").to_string();
    let target = parts.next().unwrap_or("").to_string();
    let mut headers = HashMap::new();
    loop {
        let mut h = String::new();
        if r.read_line(&mut h)? == 0 || h.trim().is_empty() {
            break;
        }
        if let Some((k, v)) = h.split_once(':') {
            headers.insert(k.trim().to_ascii_lowercase(), v.trim().to_string());
        }
    }
    let path = target.split('?').next().unwrap_or("").to_string();
    let req =
        Req { cdn: is_cdn, method: method.clone(), path: path.clone(), auth: headers.get("authorization").cloned(), range: headers.get("range").cloned() };
    state.lock().unwrap().log.push(req.clone());
    let head = method == "HEAD";
    let mut w = s;
    if is_cdn {
        let sha = path.trim_start_matches("/blobs/");
        let found = state.lock().unwrap().repos.values().flat_map(|r| r.files.clone()).find(|(_, f)| sha256_hex(&f.content) == sha);
        return match found {
            Some((p, f)) => body(&mut w, state, &req, &p, &f.content, &[], head),
            None => respond(&mut w, 404, &[], b"", head),
        };
    }
    let st = state.lock().unwrap();
    if let Some(rest) = path.strip_prefix("/api/models/") {
        // /api/models/OWNER/REPO/revision/REV
        let p: Vec<&str> = rest.splitn(4, '/').collect();
        let name = format!("{}/{}", p[0], p.get(1).unwrap_or(&""));
        let Some(repo) = st.repos.get(&name).cloned() else {
            drop(st);
            return respond(&mut w, 401, &[("X-Error-Code", "RepoNotFound"), ("X-Error-Message", "Repository not found")], b"{}", head);
        };
        drop(st);
        let siblings: Vec<String> = repo.files.iter().map(|(p, _)| format!("{{\"rfilename\":\"{p}\"}}")).collect();
        let json = format!("{{\"id\":\"{name}\",\"sha\":\"{}\",\"siblings\":[{}]}}", repo.commit, siblings.join(","));
        return respond(&mut w, 200, &[("Content-Type", "application/json")], json.as_bytes(), head);
    }
    // /OWNER/REPO/resolve/REV/PATH
    let p: Vec<&str> = path.trim_start_matches('/').splitn(5, '/').collect();
    if p.len() != 5 || p[2] != "resolve" {
        drop(st);
        return respond(&mut w, 404, &[], b"", head);
    }
    let name = format!("{}/{}", p[0], p[1]);
    if let Some(new) = st.aliases.get(&name) {
        let loc = format!("/{new}/resolve/{}/{}", p[3], p[4]);
        drop(st);
        return respond(&mut w, 307, &[("Location", &loc)], b"", head);
    }
    let rev = p[3].replace("%2F", "/");
    let file_path = p[4].to_string();
    let auth_token = req.auth.as_deref().and_then(|a| a.strip_prefix("Bearer ")).map(str::to_string);
    if auth_token.as_deref().is_some_and(|t| t.starts_with("invalid")) {
        drop(st);
        return respond(&mut w, 401, &[("X-Error-Message", "Invalid credentials in Authorization header")], b"", head);
    }
    let Some(repo) = st.repos.get(&name).cloned() else {
        drop(st);
        return respond(&mut w, 401, &[("X-Error-Code", "RepoNotFound"), ("X-Error-Message", "Repository not found")], b"", head);
    };
    drop(st);
    if let Some(allowed) = &repo.gated {
        match &auth_token {
            None => return respond(&mut w, 401, &[("X-Error-Code", "GatedRepo"), ("X-Error-Message", "Access to this repository is restricted")], b"", head),
            Some(t) if !allowed.contains(t) => {
                return respond(&mut w, 403, &[("X-Error-Code", "GatedRepo"), ("X-Error-Message", "Access to this repository is restricted")], b"", head)
            }
            _ => {}
        }
    }
    if rev != "main" && rev != repo.commit && !repo.revisions.contains(&rev) {
        return respond(&mut w, 404, &[("X-Error-Code", "RevisionNotFound"), ("X-Error-Message", "Invalid rev id")], b"", head);
    }
    let Some((_, f)) = repo.files.iter().find(|(p, _)| *p == file_path) else {
        return respond(&mut w, 404, &[("X-Error-Code", "EntryNotFound"), ("X-Error-Message", "Entry not found"), ("X-Repo-Commit", &repo.commit)], b"", head);
    };
    if f.lfs {
        let sha = sha256_hex(&f.content);
        let loc = format!("{cdn}/blobs/{sha}");
        let size = f.content.len().to_string();
        let linked = format!("\"{sha}\"");
        return respond(
            &mut w,
            302,
            &[("Location", &loc), ("X-Repo-Commit", &repo.commit), ("X-Linked-Etag", &linked), ("X-Linked-Size", &size), ("ETag", "W/\"pointer\"")],
            b"",
            head,
        );
    }
    let etag = format!("\"{}\"", git_blob_id(&f.content));
    body(&mut w, state, &req, &file_path, &f.content, &[("X-Repo-Commit", &repo.commit), ("ETag", &etag)], head)
}

/// A file's body, `Range: bytes=N-` honoured, faults applied.
fn body(w: &mut TcpStream, state: &Mutex<State>, req: &Req, name: &str, content: &[u8], extra: &[(&str, &str)], head: bool) -> std::io::Result<()> {
    let mut content = content.to_vec();
    let (cut, hold, ignore_range) = {
        let mut st = state.lock().unwrap();
        if st.corrupt && !content.is_empty() {
            let mid = content.len() / 2;
            content[mid] ^= 0xff;
        }
        let cut = if head { None } else { st.cut_next_body_after.take() };
        let hold = if head { None } else { st.hold.clone().filter(|(p, _)| name == p) };
        (cut, hold, st.ignore_range)
    };
    let start = req
        .range
        .as_deref()
        .filter(|_| !ignore_range)
        .and_then(|r| r.strip_prefix("bytes="))
        .and_then(|r| r.strip_suffix('-'))
        .and_then(|s| s.parse::<usize>().ok());
    let mut headers: Vec<(String, String)> = extra.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
    let (status, slice) = match start {
        Some(s) if s >= content.len() => return respond(w, 416, &[], b"", head),
        Some(s) => {
            headers.push(("Content-Range".into(), format!("bytes {s}-{}/{}", content.len() - 1, content.len())));
            (206, &content[s..])
        }
        None => (200, &content[..]),
    };
    let mut out = format!("HTTP/1.1 {status} X\r\nContent-Length: {}\r\nConnection: close\r\nAccept-Ranges: bytes\r\n", slice.len());
    for (k, v) in &headers {
        out.push_str(&format!("{k}: {v}\r\n"));
    }
    out.push_str("\r\n");
    w.write_all(out.as_bytes())?;
    if head {
        return Ok(());
    }
    let send = cut.map_or(slice.len(), |c| c.min(slice.len()));
    if let Some((path, heads)) = hold {
        let half = send / 2;
        w.write_all(&slice[..half])?;
        w.flush()?;
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(20) {
            let n = state.lock().unwrap().log.iter().filter(|r| r.method == "HEAD" && r.path.ends_with(&path)).count();
            if n >= heads {
                break;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        // Let the other client reach the lock.
        std::thread::sleep(Duration::from_millis(300));
        w.write_all(&slice[half..send])?;
    } else {
        w.write_all(&slice[..send])?;
    }
    w.flush()?;
    let _ = w.shutdown(std::net::Shutdown::Both);
    Ok(())
}

fn respond(w: &mut TcpStream, status: u16, headers: &[(&str, &str)], b: &[u8], head: bool) -> std::io::Result<()> {
    let mut out = format!("HTTP/1.1 {status} X\r\nContent-Length: {}\r\nConnection: close\r\n", b.len());
    for (k, v) in headers {
        out.push_str(&format!("{k}: {v}\r\n"));
    }
    out.push_str("\r\n");
    w.write_all(out.as_bytes())?;
    if !head {
        w.write_all(b)?;
    }
    w.flush()
}

/// Every file under `dir` (links listed as links), relative, sorted.
pub fn tree(dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    fn walk(root: &Path, d: &Path, out: &mut Vec<String>) {
        let Ok(rd) = std::fs::read_dir(d) else { return };
        for e in rd.flatten() {
            let p = e.path();
            let rel = p.strip_prefix(root).unwrap().to_string_lossy().into_owned();
            let ft = e.file_type().unwrap();
            if ft.is_dir() {
                walk(root, &p, out);
            } else if ft.is_symlink() {
                out.push(format!("{rel} -> {}", std::fs::read_link(&p).unwrap().display()));
            } else {
                out.push(rel);
            }
        }
    }
    walk(dir, dir, &mut out);
    out.sort();
    out
}
