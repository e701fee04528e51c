//! `mvsplat360 view`: a browser page for a render's output folder — the Gaussians in an interactive 3D viewer
//! (Spark on three.js), the video, a frame slider comparing gsplat / refined / final / GT, and `run.json`'s
//! settings, stage times and metrics.
//!
//! - [`OutDir::open`] checks a folder (`gaussians.ply`, `cameras.json`, `run.json` are required) and lists what
//!   it holds as a [`Manifest`]; the page reads only what the manifest lists and hides the rest.
//! - [`Server`] serves the page on 127.0.0.1, read-only, with only the manifest's files reachable under `/data/`.
//! - [`write_static`] writes the same page as a self-contained folder for any static web host.
//! - [`http`] is the server core `view` and `app` share: limits, the Host/Origin policy and page token, request
//!   bodies (uploads), event streams; a route is a [`http::Handler`].
//!
//! The page (`assets/index.html`) and its bundle (`assets/viewer.js`, built from `web/` by `web/build.sh`) are
//! compiled into the binary, so nothing is fetched at run time.

mod error;
pub mod http;
mod outdir;
mod server;
mod site;

pub use error::{Result, ViewerError};
pub use http::{APP_PORT, VIEW_PORT};
pub use outdir::{Manifest, OutDir, FRAME_KINDS, REQUIRED_FILES};
pub use server::{resolve, Limits, Resolved, Server};
pub use site::{asset, write_static, ASSETS};
