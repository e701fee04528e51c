//! Weights and data by name: `hf:OWNER/REPO[/PATH][@REV]`, the Hub's `…/resolve/REV/PATH` URL or a short name
//! (`dl3dv`, `vggt-1b`, …) → a local file, fetched into the Hugging Face cache exactly as the Python client
//! (`huggingface_hub`) lays it out, so that what either client downloaded — or half downloaded — is found, waited
//! for or resumed by the other. An existing local path always wins over a name.
//!
//! ```no_run
//! use mvsplat360_hub::{Hub, Quiet, Resolved};
//! let hub = Hub::from_env();
//! match hub.resolve("vggt-1b", &Quiet)? {
//!     Resolved::Path(p) => println!("{}", p.display()),
//!     Resolved::ShippedDefault => println!("the shipped model"),
//! }
//! # Ok::<(), mvsplat360_hub::Error>(())
//! ```
//!
//! Downloads are checked before they take their blob name: an LFS file's SHA-256 against `X-Linked-Etag`, a small
//! file's git blob id against `ETag`; a body shorter than announced is an interruption (the `.incomplete` file is
//! kept and resumed with `Range` next time), never a file. Environment: `HF_ENDPOINT`, `HF_HUB_CACHE` / `HF_HOME` /
//! `XDG_CACHE_HOME`, `HF_TOKEN` / `HF_TOKEN_PATH` / the token file, `HF_HUB_OFFLINE`.

mod cache;
mod download;
mod error;
mod http;
mod names;
mod unzip;

pub use cache::{Cache, FileLock};
pub use error::{Error, Result};
pub use names::{is_commit_hash, parse, short_name, HubFile, Name, ShortName, DEFAULT_REVISION, SHORT_NAMES};
pub use unzip::{unpack_zip, unpack_zip_with, UnpackLimits};

use std::path::{Path, PathBuf};

/// The Hub's address unless `HF_ENDPOINT` says otherwise.
pub const DEFAULT_ENDPOINT: &str = "https://huggingface.co";

/// What a download reports while it runs. Every method has an empty default; implementations use interior
/// mutability (an `indicatif::ProgressBar` fits as is):
///
/// ```text
/// struct Bar(indicatif::ProgressBar);
/// impl mvsplat360_hub::Progress for Bar {
///     fn note(&self, m: &str) { self.0.println(m) }
///     fn start(&self, file: &str, total: Option<u64>, from: u64) {
///         self.0.set_length(total.unwrap_or(0));
///         self.0.set_position(from);
///         self.0.set_message(file.to_string());
///     }
///     fn advance(&self, n: u64) { self.0.inc(n) }
///     fn finish(&self, _file: &str) { self.0.finish() }
/// }
/// ```
pub trait Progress: Sync {
    /// A remark worth showing: waiting for another process's download, a cached copy used because the Hub is
    /// unreachable, a file without a checksum.
    fn note(&self, _msg: &str) {}
    /// A transfer of `file` starts; `total` bytes if known, `resumed_from` of them already on disk.
    fn start(&self, _file: &str, _total: Option<u64>, _resumed_from: u64) {}
    /// `bytes` more arrived.
    fn advance(&self, _bytes: u64) {}
    /// The transfer of `file` ended (complete and checked).
    fn finish(&self, _file: &str) {}
}

/// Reports nothing.
pub struct Quiet;
impl Progress for Quiet {}

/// Where the client talks to and keeps its files; [`HubConfig::from_env`] reads it as the Python client does.
#[derive(Debug, Clone)]
pub struct HubConfig {
    /// `HF_ENDPOINT`, else https://huggingface.co (no trailing '/').
    pub endpoint: String,
    /// `HF_HUB_CACHE`, else `$HF_HOME/hub`, else `${XDG_CACHE_HOME:-~/.cache}/huggingface/hub`.
    pub cache_dir: PathBuf,
    /// `HF_TOKEN`, else the token file's content.
    pub token: Option<String>,
    /// The token file consulted (`HF_TOKEN_PATH`, else `$HF_HOME/token`), named in messages.
    pub token_path: PathBuf,
    /// `HF_HUB_OFFLINE` (1/ON/YES/TRUE): the cache only, no request.
    pub offline: bool,
}

impl HubConfig {
    /// The configuration the environment gives, with the Python client's precedence.
    pub fn from_env() -> Self {
        let var = |k: &str| std::env::var(k).ok().filter(|v| !v.is_empty());
        let home = var("HOME").map(PathBuf::from).unwrap_or_else(|| PathBuf::from("."));
        let expand = |p: String| match p.strip_prefix("~/") {
            Some(rest) => home.join(rest),
            None if p == "~" => home.clone(),
            None => PathBuf::from(p),
        };
        let xdg = var("XDG_CACHE_HOME").map(&expand).unwrap_or_else(|| home.join(".cache"));
        let hf_home = var("HF_HOME").map(&expand).unwrap_or_else(|| xdg.join("huggingface"));
        let cache_dir = var("HF_HUB_CACHE").or_else(|| var("HUGGINGFACE_HUB_CACHE")).map(&expand).unwrap_or_else(|| hf_home.join("hub"));
        let token_path = var("HF_TOKEN_PATH").map(&expand).unwrap_or_else(|| hf_home.join("token"));
        let token = var("HF_TOKEN")
            .or_else(|| var("HUGGING_FACE_HUB_TOKEN"))
            .map(|t| t.trim().to_string())
            .or_else(|| std::fs::read_to_string(&token_path).ok().map(|t| t.trim().to_string()))
            .filter(|t| !t.is_empty());
        let truthy = |k: &str| var(k).is_some_and(|v| matches!(v.to_ascii_uppercase().as_str(), "1" | "ON" | "YES" | "TRUE"));
        let offline = truthy("HF_HUB_OFFLINE") || truthy("TRANSFORMERS_OFFLINE");
        let endpoint = var("HF_ENDPOINT").unwrap_or_else(|| DEFAULT_ENDPOINT.to_string()).trim_end_matches('/').to_string();
        Self { endpoint, cache_dir, token, token_path, offline }
    }
}

/// What a name resolved to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Resolved {
    /// A local file or folder: the existing path given, or the cached download.
    Path(PathBuf),
    /// `default`: the model shipped with the project; the caller knows where it lives.
    ShippedDefault,
}

/// A short name with its state in the cache (for `weights list`).
#[derive(Debug, Clone)]
pub struct ShortNameStatus {
    /// The table's entry.
    pub entry: &'static ShortName,
    /// The cached file, if the cache holds it for the entry's revision.
    pub cached: Option<PathBuf>,
    /// Its size in bytes, when cached.
    pub size: Option<u64>,
}

/// The client: a cache, an endpoint, a token, offline or not.
pub struct Hub {
    config: HubConfig,
    cache: Cache,
    http: http::Http,
}

impl Hub {
    /// The client the environment configures ([`HubConfig::from_env`]).
    pub fn from_env() -> Self {
        Self::new(HubConfig::from_env())
    }

    /// A client with this configuration.
    pub fn new(config: HubConfig) -> Self {
        let cache = Cache::new(config.cache_dir.clone());
        let http = http::Http::new(&config.endpoint, config.token.clone());
        Self { config, cache, http }
    }

    /// Its configuration.
    pub fn config(&self) -> &HubConfig {
        &self.config
    }

    /// Its cache.
    pub fn cache(&self) -> &Cache {
        &self.cache
    }

    /// Parses a name against this client's endpoint (no file-system check, no request).
    pub fn parse(&self, spec: &str) -> Result<Name> {
        names::parse(spec, &self.config.endpoint)
    }

    /// An existing path as is; else the name's file (or folder), from the cache or downloaded into it.
    pub fn resolve(&self, spec: &str, progress: &dyn Progress) -> Result<Resolved> {
        if Path::new(spec).exists() {
            return Ok(Resolved::Path(PathBuf::from(spec)));
        }
        match self.parse(spec)? {
            Name::ShippedDefault => Ok(Resolved::ShippedDefault),
            Name::Hub(f) => self.fetch(&f, progress).map(Resolved::Path),
        }
    }

    /// [`Hub::resolve`], with `default` standing for `shipped_default`.
    pub fn resolve_or(&self, spec: &str, shipped_default: &Path, progress: &dyn Progress) -> Result<PathBuf> {
        match self.resolve(spec, progress)? {
            Resolved::Path(p) => Ok(p),
            Resolved::ShippedDefault => Ok(shipped_default.to_path_buf()),
        }
    }

    /// The cached file of a name, without any request (`None`: not cached, or not a Hub name).
    pub fn cached(&self, spec: &str) -> Option<PathBuf> {
        match self.parse(spec).ok()? {
            Name::Hub(f) => self.cache.cached(&f),
            Name::ShippedDefault => None,
        }
    }

    /// The short names and whether each is cached (no request).
    pub fn short_names(&self) -> Vec<ShortNameStatus> {
        SHORT_NAMES
            .iter()
            .map(|entry| {
                let cached = self.cached(entry.name);
                let size = cached.as_ref().and_then(|p| std::fs::metadata(p).ok()).filter(|m| m.is_file()).map(|m| m.len());
                ShortNameStatus { entry, cached, size }
            })
            .collect()
    }

    /// A Hub file (or, without a path, every file of the repository at that revision: its snapshot folder).
    pub fn fetch(&self, file: &HubFile, progress: &dyn Progress) -> Result<PathBuf> {
        match &file.path {
            Some(p) => self.fetch_file(&file.repo, &file.revision, p, progress),
            None => self.fetch_repo(&file.repo, &file.revision, progress),
        }
    }
}
