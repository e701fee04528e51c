//! A render output folder: what must be there, and the list of what is (the page's manifest).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::{io, Result, ViewerError};

/// Files without which there is nothing to show.
pub const REQUIRED_FILES: [&str; 3] = ["gaussians.ply", "cameras.json", "run.json"];
/// Optional files: the page's key for each.
const OPTIONAL_FILES: [(&str, &str); 3] = [("metrics", "metrics.json"), ("video", "video.mp4"), ("compare", "compare.mp4")];
/// `frames/<kind>/NNNN.png` folders, in the page's order.
pub const FRAME_KINDS: [&str; 4] = ["gsplat", "refined", "final", "gt"];

/// What the page may read, relative to the data prefix. Also the server's allow-list: no other file is served.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Manifest {
    /// URL prefix of the data files (relative to the page).
    pub data: String,
    /// Page key (`gaussians`, `cameras`, `run`, `metrics`, `video`, `compare`) → path in the folder.
    pub files: BTreeMap<String, String>,
    /// Frame kind → file names (`0000.png`, …), sorted; kinds without frames are left out.
    pub frames: BTreeMap<String, Vec<String>>,
}

impl Manifest {
    /// Every served path (relative, `/`-separated).
    pub fn paths(&self) -> impl Iterator<Item = String> + '_ {
        let frames = self.frames.iter().flat_map(|(k, names)| names.iter().map(move |n| format!("frames/{k}/{n}")));
        self.files.values().cloned().chain(frames)
    }

    pub fn contains(&self, rel: &str) -> bool {
        if let Some(rest) = rel.strip_prefix("frames/") {
            return rest.split_once('/').is_some_and(|(k, n)| self.frames.get(k).is_some_and(|v| v.binary_search(&n.to_string()).is_ok()));
        }
        self.files.values().any(|f| f == rel)
    }
}

/// The fields of `cameras.json` the page relies on (checked here so a bad file is one clear error, not a blank page).
#[derive(Deserialize)]
struct CamerasFile {
    cameras: Vec<CameraEntry>,
}

#[derive(Deserialize)]
#[allow(dead_code)] // parsed to validate the file; the page reads the values
struct CameraEntry {
    role: String,
    c2w: [[f64; 4]; 4],
    #[serde(rename = "K")]
    k: [[f64; 3]; 3],
    width: u32,
    height: u32,
}

/// A checked render output folder.
#[derive(Debug, Clone)]
pub struct OutDir {
    /// Canonical path (symlinks resolved): served files must resolve inside it.
    pub root: PathBuf,
}

impl OutDir {
    /// Check that `dir` is a render output folder: the required files exist and `cameras.json` / `run.json` parse.
    pub fn open(dir: &Path) -> Result<Self> {
        if !dir.is_dir() {
            return Err(ViewerError::NotADir { dir: dir.to_path_buf() });
        }
        for f in REQUIRED_FILES {
            if !dir.join(f).is_file() {
                return Err(ViewerError::MissingFile { dir: dir.to_path_buf(), file: f });
            }
        }
        let root = dir.canonicalize().map_err(io(dir))?;
        let cams_path = root.join("cameras.json");
        let cams: CamerasFile = read_json(&cams_path)?;
        if cams.cameras.is_empty() {
            return Err(ViewerError::BadFile { path: cams_path, msg: "no cameras".into() });
        }
        if let Some(c) = cams.cameras.iter().find(|c| c.width == 0 || c.height == 0 || c.k[0][0] <= 0.0 || c.k[1][1] <= 0.0) {
            return Err(ViewerError::BadFile { path: cams_path, msg: format!("a {} camera has an empty image size or focal length", c.role) });
        }
        let run_path = root.join("run.json");
        let run: serde_json::Value = read_json(&run_path)?;
        if !run.is_object() {
            return Err(ViewerError::BadFile { path: run_path, msg: "expected a JSON object".into() });
        }
        Ok(Self { root })
    }

    /// What the folder holds now (re-read on every call: a render may still be writing frames).
    pub fn manifest(&self) -> Manifest {
        let mut files = BTreeMap::new();
        for (key, f) in [("gaussians", "gaussians.ply"), ("cameras", "cameras.json"), ("run", "run.json")].into_iter().chain(OPTIONAL_FILES) {
            if self.root.join(f).is_file() {
                files.insert(key.to_string(), f.to_string());
            }
        }
        let mut frames = BTreeMap::new();
        for kind in FRAME_KINDS {
            let names = frame_names(&self.root.join("frames").join(kind));
            if !names.is_empty() {
                frames.insert(kind.to_string(), names);
            }
        }
        Manifest { data: "data/".into(), files, frames }
    }
}

fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(io(path))?;
    serde_json::from_str(&text).map_err(|e| ViewerError::BadFile { path: path.to_path_buf(), msg: e.to_string() })
}

/// `NNNN.png` files of a frame folder, sorted (temporary files of a running render are skipped by the pattern).
fn frame_names(dir: &Path) -> Vec<String> {
    let Ok(rd) = std::fs::read_dir(dir) else { return Vec::new() };
    let mut v: Vec<String> = rd
        .flatten()
        .filter(|e| e.path().is_file())
        .filter_map(|e| e.file_name().into_string().ok())
        .filter(|n| n.len() == 8 && n.ends_with(".png") && n[..4].bytes().all(|b| b.is_ascii_digit()))
        .collect();
    v.sort();
    v
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cameras() -> &'static str {
        r#"{"cameras":[{"role":"target","c2w":[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]],"K":[[100,0,64],[0,100,32],[0,0,1]],"width":128,"height":64}]}"#
    }

    fn minimal(dir: &Path) {
        std::fs::write(dir.join("gaussians.ply"), b"ply\n").unwrap();
        std::fs::write(dir.join("cameras.json"), cameras()).unwrap();
        std::fs::write(dir.join("run.json"), "{}").unwrap();
    }

    #[test]
    fn each_missing_required_file_is_named() {
        for f in REQUIRED_FILES {
            let t = tempfile::tempdir().unwrap();
            minimal(t.path());
            std::fs::remove_file(t.path().join(f)).unwrap();
            let e = OutDir::open(t.path()).unwrap_err().to_string();
            assert!(e.contains(f) && e.contains("missing"), "{e}");
        }
        let e = OutDir::open(Path::new("/definitely/not/here")).unwrap_err().to_string();
        assert!(e.contains("not a folder"), "{e}");
    }

    #[test]
    fn bad_cameras_json_is_an_error() {
        let t = tempfile::tempdir().unwrap();
        minimal(t.path());
        std::fs::write(t.path().join("cameras.json"), r#"{"cameras":[]}"#).unwrap();
        assert!(OutDir::open(t.path()).unwrap_err().to_string().contains("no cameras"));
        std::fs::write(t.path().join("cameras.json"), "{").unwrap();
        assert!(OutDir::open(t.path()).unwrap_err().to_string().contains("cameras.json"));
    }

    #[test]
    fn manifest_lists_only_what_exists() {
        let t = tempfile::tempdir().unwrap();
        minimal(t.path());
        let m = OutDir::open(t.path()).unwrap().manifest();
        assert_eq!(m.files.len(), 3);
        assert!(m.frames.is_empty());
        for k in ["gsplat", "gt"] {
            std::fs::create_dir_all(t.path().join("frames").join(k)).unwrap();
        }
        std::fs::write(t.path().join("frames/gsplat/0001.png"), b"x").unwrap();
        std::fs::write(t.path().join("frames/gsplat/0000.png"), b"x").unwrap();
        std::fs::write(t.path().join("frames/gsplat/.0002.png.tmp"), b"x").unwrap();
        std::fs::write(t.path().join("video.mp4"), b"x").unwrap();
        let m = OutDir::open(t.path()).unwrap().manifest();
        assert_eq!(m.frames["gsplat"], vec!["0000.png", "0001.png"]);
        assert!(!m.frames.contains_key("gt") && !m.frames.contains_key("refined"));
        assert_eq!(m.files.get("video").map(String::as_str), Some("video.mp4"));
        assert!(m.contains("frames/gsplat/0001.png") && m.contains("run.json"));
        assert!(!m.contains("frames/gsplat/.0002.png.tmp") && !m.contains("frames/gt/0000.png") && !m.contains("x"));
    }
}
