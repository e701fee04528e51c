use std::path::PathBuf;

pub type Result<T> = std::result::Result<T, ViewerError>;

#[derive(Debug, thiserror::Error)]
pub enum ViewerError {
    #[error("{dir}: not a folder (pass the --out folder of `mvsplat360 render`)", dir = .dir.display())]
    NotADir { dir: PathBuf },
    #[error("{dir}: {file} is missing; a render folder needs gaussians.ply, cameras.json and run.json (run `mvsplat360 render … --out {dir}`)", dir = .dir.display())]
    MissingFile { dir: PathBuf, file: &'static str },
    #[error("{path}: {msg}", path = .path.display())]
    BadFile { path: PathBuf, msg: String },
    #[error("{path}: {source}", path = .path.display())]
    Io { path: PathBuf, source: std::io::Error },
    #[error("port {port} on {host} is already in use (by another program, or another mvsplat360 server): pass --port with a free port, or --port 0 for any free one")]
    PortInUse { host: String, port: u16 },
    #[error("cannot listen on {addr}: {msg} (try another --port, or --port 0 for any free one)")]
    Bind { addr: String, msg: String },
    #[error("{path}: {msg}", path = .path.display())]
    StaticDest { path: PathBuf, msg: String },
}

pub(crate) fn io(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> ViewerError {
    let path = path.into();
    move |source| ViewerError::Io { path, source }
}
