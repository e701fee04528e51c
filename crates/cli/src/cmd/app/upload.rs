//! Uploads: a page asks for an upload id (nothing written), then `PUT`s each file into `WORKDIR/.staging/ID/`
//! (made on the first file). Every file is checked before it is kept: photos decoded within the image reader's
//! limits, a video probed with ffprobe, `transforms.json` parsed; anything else is refused and removed. A job
//! takes the folder whole ([`Staging::take`]); folders not taken within [`ABANDONED`] are removed.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use mvsplat360_viewer::http::{safe_file_name, Body, BodyError, PageToken, Response};

/// An upload untouched this long is abandoned (its folder removed).
pub const ABANDONED: Duration = Duration::from_secs(3600);

const PHOTO_EXT: [&str; 3] = ["jpg", "jpeg", "png"];
const VIDEO_EXT: [&str; 6] = ["mp4", "mov", "mkv", "webm", "avi", "m4v"];

/// What an upload folder holds.
#[derive(Debug, Default, Clone)]
struct Upload {
    /// Bytes taken or being taken (reserved when a file starts).
    bytes: u64,
    photos: Vec<String>,
    videos: Vec<String>,
    transforms: bool,
    touched: Option<Instant>,
}

/// The staging area: `WORKDIR/.staging`, removed whole when the app starts and stops.
pub struct Staging {
    pub root: PathBuf,
    /// Bytes one upload may hold (`--max-upload`).
    pub max: u64,
    ffprobe: PathBuf,
    uploads: Mutex<HashMap<String, Upload>>,
}

fn ext(name: &str) -> String {
    Path::new(name).extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase()
}

impl Staging {
    pub fn new(workdir: &Path, max: u64) -> Self {
        let root = workdir.join(".staging");
        let _ = std::fs::remove_dir_all(&root);
        let ffprobe = std::env::var_os("FFPROBE").map(PathBuf::from).unwrap_or_else(|| PathBuf::from("ffprobe"));
        Self { root, max, ffprobe, uploads: Mutex::new(HashMap::new()) }
    }

    /// A new upload's id (nothing written until its first file).
    pub fn open(&self) -> String {
        self.sweep();
        let id = PageToken::random().as_str()[..16].to_string();
        let up = Upload { touched: Some(Instant::now()), ..Upload::default() };
        self.uploads.lock().unwrap().insert(id.clone(), up);
        id
    }

    /// Remove uploads untouched for [`ABANDONED`].
    fn sweep(&self) {
        let mut ups = self.uploads.lock().unwrap();
        let old: Vec<String> = ups.iter().filter(|(_, u)| u.touched.is_some_and(|t| t.elapsed() > ABANDONED)).map(|(k, _)| k.clone()).collect();
        for id in old {
            ups.remove(&id);
            let _ = std::fs::remove_dir_all(self.root.join(&id));
        }
    }

    /// `PUT /api/uploads/ID/NAME`: take one file.
    pub fn put(&self, id: &str, raw_name: &str, body: &mut Body<'_>) -> Response {
        let Some(name) = safe_file_name(raw_name) else { return BodyError::BadName.response() };
        let kind = ext(&name);
        let is_transforms = name == "transforms.json";
        if !is_transforms && !PHOTO_EXT.contains(&kind.as_str()) && !VIDEO_EXT.contains(&kind.as_str()) {
            return Response::text(415, "only photos (.jpg, .jpeg, .png), a video (.mp4, .mov, .mkv, .webm, .avi, .m4v) and transforms.json are taken");
        }
        let Some(len) = body.len() else { return BodyError::LengthRequired.response() };
        // Reserve the bytes before anything is written, so uploads at once cannot pass the limit together.
        {
            let mut ups = self.uploads.lock().unwrap();
            let Some(up) = ups.get_mut(id) else { return Response::text(404, "no such upload (reload the page)") };
            if up.bytes.saturating_add(len) > self.max {
                let left = self.max.saturating_sub(up.bytes);
                let e = BodyError::TooLarge { len, max: left };
                return Response::text(413, &format!("{e}: an upload holds at most {} bytes (--max-upload)", self.max));
            }
            up.bytes += len;
            up.touched = Some(Instant::now());
        }
        let dir = self.root.join(id);
        let saved = std::fs::create_dir_all(&dir).map_err(BodyError::Sink).and_then(|_| {
            let _ = std::fs::remove_file(dir.join(&name));
            body.save_into(&dir, raw_name, len)
        });
        let checked = saved.map_err(|e| e.response()).and_then(|path| self.check(&path, &name, &kind, is_transforms));
        let mut ups = self.uploads.lock().unwrap();
        let Some(up) = ups.get_mut(id) else { return Response::text(404, "no such upload") };
        match checked {
            Ok(()) => {
                if is_transforms {
                    up.transforms = true;
                } else if VIDEO_EXT.contains(&kind.as_str()) {
                    up.videos.push(name.clone());
                } else {
                    up.photos.push(name.clone());
                }
                Response::json(200, &serde_json::json!({"name": name, "bytes": len}))
            }
            Err(r) => {
                up.bytes -= len;
                let _ = std::fs::remove_file(dir.join(&name));
                if up.bytes == 0 && up.photos.is_empty() && up.videos.is_empty() && !up.transforms {
                    let _ = std::fs::remove_dir(&dir);
                }
                r
            }
        }
    }

    /// The file is what its name says: a decodable photo, a video ffprobe reads, a JSON file.
    fn check(&self, path: &Path, name: &str, kind: &str, transforms: bool) -> Result<(), Response> {
        let refuse = |msg: String| Err(Response::text(415, &format!("{name}: {msg}")));
        if transforms {
            let ok = std::fs::read(path).ok().and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok()).is_some_and(|v| v["frames"].is_array());
            return if ok { Ok(()) } else { refuse("not a transforms.json with a frames list".into()) };
        }
        if VIDEO_EXT.contains(&kind) {
            return match mvsplat360_pose::video::probe(&self.ffprobe, path) {
                Ok(_) => Ok(()),
                Err(e) => refuse(format!("not a readable video ({e})")),
            };
        }
        match mvsplat360_dataset::ImageSource::File(path.to_path_buf()).decode() {
            Ok(_) => Ok(()),
            Err(e) => refuse(format!("not a readable photo ({e})")),
        }
    }

    /// Take an upload for a job: its folder moved to `dest`, laid out as `render` reads it. Returns a
    /// description of the input and the path `render` reads.
    pub fn take(&self, id: &str, dest: &Path) -> Result<(String, PathBuf), String> {
        let up = self.uploads.lock().unwrap().get(id).cloned().ok_or("no such upload (reload the page)")?;
        let input = match (up.videos.len(), up.photos.len()) {
            (0, 0) => return Err("the upload holds no photos or video".into()),
            (1, 0) if !up.transforms => None,
            (0, _) => Some(()),
            _ => return Err("give either photos (with or without transforms.json) or one video, not both".into()),
        };
        let src = self.root.join(id);
        std::fs::rename(&src, dest).map_err(|e| format!("moving the upload into {}: {e}", dest.display()))?;
        self.uploads.lock().unwrap().remove(id);
        if input.is_none() {
            let v = &up.videos[0];
            return Ok((format!("a video ({v})"), dest.join(v)));
        }
        if up.transforms {
            place_by_transforms(dest, &up.photos)?;
            return Ok((format!("{} photos + transforms.json", up.photos.len()), dest.to_path_buf()));
        }
        Ok((format!("{} photos", up.photos.len()), dest.to_path_buf()))
    }

    /// Remove every upload (the app stops).
    pub fn clear(&self) {
        let _ = std::fs::remove_dir_all(&self.root);
    }
}

/// Photos uploaded flat beside a `transforms.json` whose frames name them in subfolders (`images/000.jpg`):
/// moved to where it names them (each a plain relative path inside `dir`).
fn place_by_transforms(dir: &Path, photos: &[String]) -> Result<(), String> {
    let t: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("transforms.json")).map_err(|e| e.to_string())?).map_err(|e| format!("transforms.json: {e}"))?;
    for f in t["frames"].as_array().into_iter().flatten() {
        let Some(rel) = f["file_path"].as_str() else { continue };
        let rel = rel.trim_start_matches("./");
        let plain = !rel.is_empty() && !rel.starts_with('/') && !rel.contains(['\\', '\0']) && rel.split('/').all(|s| !s.is_empty() && s != "." && s != "..");
        let Some(base) = rel.rsplit('/').next() else { continue };
        if !plain || rel == base || !photos.iter().any(|p| p == base) {
            continue;
        }
        let to = dir.join(rel);
        if let Some(parent) = to.parent() {
            std::fs::create_dir_all(parent).map_err(|e| e.to_string())?;
        }
        std::fs::rename(dir.join(base), &to).map_err(|e| format!("placing {base} at {rel}: {e}"))?;
    }
    Ok(())
}
