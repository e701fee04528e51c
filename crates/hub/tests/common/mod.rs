//! The Hub stand-in (`mvsplat360_testkit::hub_standin`) and what only these tests need: a client of it with its
//! own cache, progress that records notes.
#![allow(dead_code)]

pub use mvsplat360_testkit::hub_standin::*;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

pub trait StandInHub {
    /// A client of this stand-in with its own cache.
    fn hub(&self, cache: &Path, token: Option<&str>, offline: bool) -> mvsplat360_hub::Hub;
}

impl StandInHub for StandIn {
    fn hub(&self, cache: &Path, token: Option<&str>, offline: bool) -> mvsplat360_hub::Hub {
        mvsplat360_hub::Hub::new(mvsplat360_hub::HubConfig {
            endpoint: self.endpoint.clone(),
            cache_dir: cache.to_path_buf(),
            token: token.map(str::to_string),
            token_path: PathBuf::from("/nonexistent/token"),
            offline,
        })
    }
}

/// Progress that records notes.
#[derive(Default)]
pub struct Notes(pub Mutex<Vec<String>>, pub Mutex<Vec<(String, Option<u64>, u64)>>);
impl mvsplat360_hub::Progress for Notes {
    fn note(&self, m: &str) {
        self.0.lock().unwrap().push(m.to_string());
    }
    fn start(&self, f: &str, total: Option<u64>, from: u64) {
        self.1.lock().unwrap().push((f.to_string(), total, from));
    }
}
