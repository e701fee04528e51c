//! pixelSplat/MVSplat/MVSplat360 `.torch` chunks: a `torch.save`d list of dicts
//! `{key, url, timestamps int64[N], images: [uint8 1-D encoded JPEG/PNG], cameras float32[N,18]}` with
//! camera rows `[fx/W, fy/H, cx/W, cy/H, 0, 0, w2c 3×4 row-major]` (OpenCV axes), plus an `index.json`
//! mapping scene keys to chunk file names. The zip/pickle container is parsed with candle's unpickler.

use std::collections::HashMap;
use std::io::Read;
use std::path::Path;
use std::sync::Arc;

use candle_core::pickle::{Object, Stack};
use candle_core::DType;
use mvsplat360_camera::convert::{to_array, w2c_3x4_to_c2w};
use mvsplat360_camera::Camera;

use crate::error::io;
use crate::{DatasetError, ImageSource, Scene};

fn bad(path: &Path, msg: impl Into<String>) -> DatasetError {
    DatasetError::Chunk { path: path.to_path_buf(), msg: msg.into() }
}

/// One scene of a chunk, images still encoded.
#[derive(Debug, Clone)]
pub struct ChunkScene {
    pub key: String,
    pub url: String,
    pub timestamps: Vec<i64>,
    pub images: Vec<Arc<Vec<u8>>>,
    /// Raw 18-float camera rows.
    pub cameras: Vec<[f32; 18]>,
}

struct Archive<'a> {
    path: &'a Path,
    zip: zip::ZipArchive<std::io::BufReader<std::fs::File>>,
    dir: std::path::PathBuf,
    cache: HashMap<String, Vec<u8>>,
}

impl Archive<'_> {
    /// Raw little-endian bytes of a pickled tensor (contiguous tensors only, as torch.save writes them here).
    fn tensor_bytes(&mut self, obj: Object, what: &str) -> Result<(DType, Vec<usize>, Vec<u8>), DatasetError> {
        // candle's tensor rebuild indexes the pickled tuples unchecked: a malformed one panics (tests/fuzz.rs).
        let info = crate::guard::catch_quietly(|| obj.into_tensor_info(Object::Unicode(what.to_string()), &self.dir))
            .map_err(|msg| bad(self.path, format!("{what}: malformed tensor record ({msg})")))?
            .map_err(|e| bad(self.path, format!("{what}: {e}")))?
            .ok_or_else(|| bad(self.path, format!("{what}: expected a tensor")))?;
        if !info.layout.is_contiguous() {
            return Err(bad(self.path, format!("{what}: non-contiguous tensor; re-save it with .contiguous()")));
        }
        if !self.cache.contains_key(&info.path) {
            let mut entry = self.zip.by_name(&info.path).map_err(|e| bad(self.path, format!("{what}: storage {} missing: {e}", info.path)))?;
            // The size is the archive's claim: never reserve more than the file holds.
            let file_len = std::fs::metadata(self.path).map(|m| m.len()).unwrap_or(0);
            let mut buf = Vec::with_capacity(entry.size().min(file_len) as usize);
            entry.read_to_end(&mut buf).map_err(|e| io(self.path, e))?;
            self.cache.insert(info.path.clone(), buf);
        }
        let storage = &self.cache[&info.path];
        let start = info.layout.start_offset();
        let short = || bad(self.path, format!("{what}: storage {} is shorter than the tensor", info.path));
        let len = info.layout.dims().iter().try_fold(info.dtype.size_in_bytes(), |a, &d| a.checked_mul(d)).ok_or_else(short)?;
        let bytes = storage.get(start..start.checked_add(len).ok_or_else(short)?).ok_or_else(short)?;
        Ok((info.dtype, info.layout.dims().to_vec(), bytes.to_vec()))
    }
}

fn dict_get(items: &mut Vec<(Object, Object)>, key: &str) -> Option<Object> {
    let pos = items.iter().position(|(k, _)| matches!(k, Object::Unicode(s) if s == key))?;
    Some(items.swap_remove(pos).1)
}

/// Read every scene of a chunk file.
pub fn read_chunk(path: &Path) -> Result<Vec<ChunkScene>, DatasetError> {
    let file = std::fs::File::open(path).map_err(|e| io(path, e))?;
    let mut zip = zip::ZipArchive::new(std::io::BufReader::new(file))
        .map_err(|e| bad(path, format!("not a torch zip archive ({e}); chunks must be written by torch.save")))?;
    let pkl = zip
        .file_names()
        .filter_map(|n| n.ok().map(|n| n.into_owned()))
        .find(|n| n.ends_with("data.pkl"))
        .ok_or_else(|| bad(path, "no data.pkl in the archive"))?;
    let root = {
        let entry = zip.by_name(&pkl).map_err(|e| bad(path, e.to_string()))?;
        let mut reader = std::io::BufReader::new(entry);
        // candle's unpickler can panic on a crafted pickle (found by tests/fuzz.rs: a LONG1 of more than 8
        // bytes overflows a shift); the file is then refused like any other malformed one.
        let unpickled = crate::guard::catch_quietly(|| {
            let mut stack = Stack::empty();
            stack.read_loop(&mut reader)?;
            stack.finalize()
        });
        match unpickled {
            Ok(Ok(root)) => root,
            Ok(Err(e)) => return Err(bad(path, format!("unpickling failed: {e}"))),
            Err(msg) => return Err(bad(path, format!("unpickling failed: malformed pickle ({msg})"))),
        }
    };
    let dir = std::path::PathBuf::from(pkl.trim_end_matches(".pkl"));
    let mut ar = Archive { path, zip, dir, cache: HashMap::new() };
    let Object::List(items) = root else {
        return Err(bad(path, "top-level object is not a list of scene dicts"));
    };
    let mut scenes = vec![];
    for (si, item) in items.into_iter().enumerate() {
        let Object::Dict(mut d) = item else {
            return Err(bad(path, format!("item {si} is not a dict")));
        };
        let key = match dict_get(&mut d, "key") {
            Some(Object::Unicode(s)) => s,
            _ => return Err(bad(path, format!("item {si}: field `key` missing or not a string"))),
        };
        let url = match dict_get(&mut d, "url") {
            Some(Object::Unicode(s)) => s,
            _ => String::new(),
        };
        let field = |name: &str| format!("scene {key}: field `{name}`");
        let cams_obj = dict_get(&mut d, "cameras").ok_or_else(|| bad(path, format!("{} missing", field("cameras"))))?;
        let (dt, dims, bytes) = ar.tensor_bytes(cams_obj, &field("cameras"))?;
        if dt != DType::F32 || dims.len() != 2 || dims[1] != 18 {
            return Err(bad(path, format!("{} must be float32 [N,18], found {dt:?} {dims:?}", field("cameras"))));
        }
        let floats: Vec<f32> = bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
        let cameras: Vec<[f32; 18]> = floats.chunks_exact(18).map(|r| std::array::from_fn(|i| r[i])).collect();
        let timestamps = match dict_get(&mut d, "timestamps") {
            Some(obj) => {
                let (dt, _, bytes) = ar.tensor_bytes(obj, &field("timestamps"))?;
                if dt != DType::I64 {
                    return Err(bad(path, format!("{} must be int64", field("timestamps"))));
                }
                bytes.chunks_exact(8).map(|b| i64::from_le_bytes(b.try_into().unwrap_or_default())).collect()
            }
            None => (0..cameras.len() as i64).collect(),
        };
        let Some(Object::List(imgs)) = dict_get(&mut d, "images") else {
            return Err(bad(path, format!("{} missing or not a list of tensors", field("images"))));
        };
        let mut images = vec![];
        for (vi, obj) in imgs.into_iter().enumerate() {
            let what = format!("scene {key}: images[{vi}]");
            let (dt, dims, bytes) = ar.tensor_bytes(obj, &what)?;
            if dt != DType::U8 || dims.len() != 1 {
                return Err(bad(path, format!("{what} must be a 1-D uint8 tensor of encoded image bytes")));
            }
            images.push(Arc::new(bytes));
        }
        if images.len() != cameras.len() {
            return Err(bad(path, format!("scene {key}: {} images but {} camera rows", images.len(), cameras.len())));
        }
        scenes.push(ChunkScene { key, url, timestamps, images, cameras });
        ar.cache.clear();
    }
    Ok(scenes)
}

impl ChunkScene {
    /// Convert to a [`Scene`]: image sizes come from the encoded headers, intrinsics are de-normalised.
    pub fn into_scene(self, path: &Path) -> Result<Scene, DatasetError> {
        let mut scene = Scene { name: self.key.clone(), ..Scene::default() };
        for (i, (bytes, row)) in self.images.into_iter().zip(&self.cameras).enumerate() {
            let source = ImageSource::Encoded { label: format!("{}: scene {} view {i}", path.display(), self.key), bytes };
            let (w, h) = source.dimensions()?;
            let w2c: [f64; 12] = std::array::from_fn(|k| row[6 + k] as f64);
            let k = [row[0] as f64, row[1] as f64, row[2] as f64, row[3] as f64];
            scene.cameras.push(Camera::from_normalized(k, w, h, to_array(&w2c_3x4_to_c2w(&w2c))));
            scene.view_names.push(format!("{}[{}]", self.key, self.timestamps.get(i).copied().unwrap_or(i as i64)));
            scene.images.push(source);
        }
        Ok(scene)
    }
}

/// Read one scene of a chunk: by key, or the first.
pub fn read_scene(path: &Path, key: Option<&str>) -> Result<Scene, DatasetError> {
    let scenes = read_chunk(path)?;
    let available = || scenes.iter().map(|s| s.key.clone()).collect::<Vec<_>>().join(", ");
    let chosen = match key {
        Some(k) => scenes.iter().position(|s| s.key == k).ok_or_else(|| bad(path, format!("no scene `{k}` (available: {})", available())))?,
        None if scenes.is_empty() => return Err(bad(path, "the chunk holds no scenes")),
        None => 0,
    };
    scenes.into_iter().nth(chosen).ok_or_else(|| bad(path, "scene vanished"))?.into_scene(path)
}

/// The chunk folder's `index.json`: scene key → chunk file name.
pub fn read_chunk_index(path: &Path) -> Result<HashMap<String, String>, DatasetError> {
    let text = std::fs::read_to_string(path).map_err(|e| io(path, e))?;
    serde_json::from_str(&text).map_err(|source| DatasetError::Json { path: path.to_path_buf(), source })
}
