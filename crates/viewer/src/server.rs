//! `view`'s routes on the shared server core ([`crate::http`]): GET/HEAD only, on 127.0.0.1 unless told
//! otherwise, the page's assets from the binary and the render's files from an allow-list (the manifest) — a
//! request can reach nothing else, whatever its encoding. A thread per connection, each with timeouts, so that no
//! client can hold the others up.

use std::path::PathBuf;
use std::sync::Arc;

use crate::error::Result;
use crate::http::{content_type, Body, HttpServer, Request, Response, Stats};
use crate::outdir::OutDir;
use crate::site::asset;

pub use crate::http::Limits;

/// What a request path refers to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Resolved {
    /// A page asset compiled into the binary (its name).
    Asset(&'static str),
    /// The manifest, generated per request.
    Manifest,
    /// A file of the output folder (canonical path inside it).
    File(PathBuf),
    /// Refused: status code and a short reason.
    Refused(u16, &'static str),
}

/// Map a raw request target (as sent, still percent-encoded) to what it may serve.
///
/// Data paths are decoded once and must then be plain relative paths (no `..`, `.`, empty segments, backslashes,
/// NUL or leading `/`) listed in the folder's manifest, and must still lie inside the folder once symlinks are
/// resolved; anything else is refused.
pub fn resolve(out: &OutDir, target: &str) -> Resolved {
    let path = target.split(['?', '#']).next().unwrap_or("");
    if !path.starts_with('/') {
        return Resolved::Refused(400, "bad request target");
    }
    match path {
        "/" | "/index.html" => return Resolved::Asset("index.html"),
        "/manifest.json" => return Resolved::Manifest,
        _ => {}
    }
    let Some(raw) = path.strip_prefix("/data/") else {
        return match asset(&path[1..]) {
            Some((name, _)) => Resolved::Asset(name),
            None => Resolved::Refused(404, "not found"),
        };
    };
    let Ok(rel) = percent_encoding::percent_decode_str(raw).decode_utf8() else {
        return Resolved::Refused(400, "bad path encoding");
    };
    let bad = rel.is_empty() || rel.starts_with('/') || rel.contains(['\\', '\0', ':']) || rel.split('/').any(|s| s.is_empty() || s == "." || s == "..");
    if bad {
        return Resolved::Refused(400, "bad path");
    }
    if !out.manifest().contains(&rel) {
        return Resolved::Refused(404, "not found");
    }
    match out.root.join(&*rel).canonicalize() {
        Ok(p) if p.starts_with(&out.root) && p.is_file() => Resolved::File(p),
        Ok(_) => Resolved::Refused(403, "outside the output folder"),
        Err(_) => Resolved::Refused(404, "not found"),
    }
}

/// `view`'s answer to a request that passed the policy checks.
fn respond(out: &OutDir, req: &Request) -> Response {
    if req.method != "GET" && req.method != "HEAD" {
        return Response::text(405, "method not allowed (read-only server)").header("Allow", "GET, HEAD");
    }
    match resolve(out, &req.target) {
        Resolved::Asset(name) => match asset(name) {
            Some((_, bytes)) => Response::bytes(200, content_type(name), bytes),
            None => Response::text(404, "not found"),
        },
        Resolved::Manifest => Response::json(200, &out.manifest()),
        Resolved::File(p) => Response::file(&p, req.header("Range")),
        Resolved::Refused(code, why) => Response::text(code, why),
    }
}

/// The page's server for one output folder.
pub struct Server {
    core: HttpServer,
    out: OutDir,
}

impl Server {
    /// Check `out` and listen on 127.0.0.1:`port` (0: any free port).
    pub fn bind(out: OutDir, port: u16) -> Result<Self> {
        Self::bind_on(out, "127.0.0.1", port, Vec::new())
    }

    /// [`Server::bind`] on the address `host` (an IP), answering also to the `Host` names in `allow_hosts`.
    pub fn bind_on(out: OutDir, host: &str, port: u16, allow_hosts: Vec<String>) -> Result<Self> {
        Ok(Self { core: HttpServer::bind(host, port)?.allow_hosts(allow_hosts), out })
    }

    /// Other timeouts and connection limit than [`Limits::default`].
    pub fn with_limits(mut self, limits: Limits) -> Self {
        self.core = self.core.with_limits(limits);
        self
    }

    /// The page's address.
    pub fn url(&self) -> &str {
        self.core.url()
    }

    /// Live counts (connections), valid while the server runs.
    pub fn stats(&self) -> Stats {
        self.core.stats()
    }

    /// Serve until the process ends: a thread per connection (a large `gaussians.ply` download must not hold up
    /// the frames and the video), each dropped when its client is idle, slow or stops reading ([`Limits`]).
    pub fn serve(self) {
        let out = Arc::new(self.out);
        self.core.serve(move |req: &Request, _body: &mut Body<'_>| respond(&out, req));
    }
}
