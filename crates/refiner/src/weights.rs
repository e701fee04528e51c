//! Strict, mmapped weight source in sgm/open_clip key names, shared by the VAE and the CLIP embedder.
//!
//! A file is read either in the model's own layout (under a prefix) or through a foreign layout's mapping
//! table (`crate::keymap::{vae, clip}`), which says for every foreign key which model tensor it feeds and how
//! (as is, reshaped, transposed, or as one slice of a concatenation). Only keys inside the model's scope are
//! checked, so a full checkpoint (UNet, conditioner, text tower, …) can be read for one component.

use std::cell::RefCell;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use candle_core::safetensors::MmapedSafetensors;
use candle_core::{DType, Device, Tensor, Var};

use crate::unet::util::WeightStore;

#[derive(Debug, thiserror::Error)]
pub enum WeightsError {
    #[error("cannot open weights {path}: {msg}")]
    Open { path: PathBuf, msg: String },
    #[error("{path}: no {what} keys recognised ({expected})")]
    UnknownLayout { path: PathBuf, what: String, expected: String },
    #[error("{path}: {what} weights do not match the config ({} missing, {} unexpected, {} wrong shape) — check the config against the checkpoint\n  missing: {missing:?}\n  unexpected: {unexpected:?}\n  wrong shape: {mismatched:?}", missing.len(), unexpected.len(), mismatched.len())]
    KeyMismatch { path: PathBuf, what: String, missing: Vec<String>, unexpected: Vec<String>, mismatched: Vec<String> },
    #[error("{path}: reading `{key}`: {source}")]
    Read { path: PathBuf, key: String, source: candle_core::Error },
}

/// How one stored tensor feeds a model tensor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Piece {
    /// Same values, same shape.
    Whole,
    /// Same values in another shape with the same element count (a Linear stored where a 1×1 conv is used).
    Reshape,
    /// 2-D transpose (transformers `visual_projection.weight` = open_clip `proj`ᵀ).
    Transpose,
    /// Slice `index` of `of` slices concatenated along dim 0 (separate q/k/v → `in_proj_weight`).
    Concat { index: usize, of: usize },
}

#[derive(Debug, Default)]
struct Recipe {
    /// (slice index, stored key, piece); one entry unless `Concat`.
    parts: Vec<(usize, String, Piece)>,
}

/// Hands out f32 tensors by model name; records missing / wrongly shaped / unused keys for [`Self::finish`].
pub struct StrictWeights {
    /// None = seeded random weights (benchmarks), see [`Self::random`].
    st: Option<MmapedSafetensors>,
    seed: u64,
    counter: RefCell<u64>,
    /// Random mode: every tensor handed out, by name (to save a random model as a state dict).
    recorded: RefCell<Vec<(String, Tensor)>>,
    path: PathBuf,
    what: String,
    recipes: BTreeMap<String, Recipe>,
    unexpected: Vec<String>,
    used: RefCell<BTreeSet<String>>,
    missing: RefCell<Vec<String>>,
    mismatched: RefCell<Vec<String>>,
    device: Device,
    /// dtype tensors are handed out in (f32 unless [`StrictWeights::with_dtype`]).
    dtype: DType,
    /// How the layers keep their products' weights (CPU bf16/f16: handed out in f32, see [`Self::store`]).
    store: WeightStore,
    /// Trainable mode: every tensor is handed out as a `Var` (listed here by model name).
    trainable: bool,
    vars: RefCell<Vec<(String, Var)>>,
}

/// Memory-map a safetensors file.
pub fn open_safetensors(path: &Path) -> Result<MmapedSafetensors, WeightsError> {
    // SAFETY: read-only mapping; the file must not be modified while mapped (same contract as candle).
    unsafe { MmapedSafetensors::new(path) }.map_err(|e| WeightsError::Open { path: path.to_path_buf(), msg: e.to_string() })
}

/// Every key of a mapped file.
pub fn keys(st: &MmapedSafetensors) -> Vec<String> {
    st.tensors().into_iter().map(|(n, _)| n).collect()
}

impl StrictWeights {
    /// Model layout: in-scope keys are those starting with `prefix` followed by one of `scopes`
    /// (e.g. `encoder.`); the model name is the key without `prefix`.
    pub fn own_layout(st: MmapedSafetensors, path: &Path, what: &str, prefix: &str, scopes: &[&str], device: &Device) -> Self {
        let mut recipes = BTreeMap::new();
        for k in keys(&st) {
            if let Some(rest) = k.strip_prefix(prefix) {
                if scopes.iter().any(|s| rest.starts_with(s)) {
                    recipes.insert(rest.to_string(), Recipe { parts: vec![(0, k.clone(), Piece::Whole)] });
                }
            }
        }
        Self::new(Some(st), path, what, recipes, Vec::new(), device)
    }

    /// Foreign layout: `map(key)` gives `Some(Some((model name, piece)))` for a mapped key, `Some(None)` for
    /// an in-scope key to ignore (buffers such as `position_ids`), `None` for an in-scope key that has no
    /// model counterpart (reported as unexpected); keys for which `in_scope` is false are skipped.
    pub fn mapped(
        st: MmapedSafetensors,
        path: &Path,
        what: &str,
        in_scope: impl Fn(&str) -> bool,
        map: impl Fn(&str) -> Option<Option<(String, Piece)>>,
        device: &Device,
    ) -> Self {
        let mut recipes: BTreeMap<String, Recipe> = BTreeMap::new();
        let mut unexpected = Vec::new();
        for k in keys(&st) {
            if !in_scope(&k) {
                continue;
            }
            match map(&k) {
                Some(Some((name, piece))) => {
                    let idx = if let Piece::Concat { index, .. } = piece { index } else { 0 };
                    recipes.entry(name).or_default().parts.push((idx, k.clone(), piece));
                }
                Some(None) => {}
                None => unexpected.push(k.clone()),
            }
        }
        for r in recipes.values_mut() {
            r.parts.sort_by_key(|p| p.0);
        }
        Self::new(Some(st), path, what, recipes, unexpected, device)
    }

    /// Seeded random weights for benchmarks: uniform ±1/√fan_in for matrices and kernels, 1 for 1-D
    /// `.weight` (norm scales), 0 for other 1-D tensors (biases, mix factors, class embedding).
    pub fn random(seed: u64, what: &str, device: &Device) -> Self {
        let mut w = Self::new(None, Path::new("<random>"), what, BTreeMap::new(), Vec::new(), device);
        w.seed = seed;
        w
    }

    fn new(st: Option<MmapedSafetensors>, path: &Path, what: &str, recipes: BTreeMap<String, Recipe>, unexpected: Vec<String>, device: &Device) -> Self {
        Self {
            st,
            seed: 0,
            counter: RefCell::new(0),
            recorded: RefCell::new(Vec::new()),
            path: path.to_path_buf(),
            what: what.to_string(),
            recipes,
            unexpected,
            used: RefCell::new(BTreeSet::new()),
            missing: RefCell::new(Vec::new()),
            mismatched: RefCell::new(Vec::new()),
            device: device.clone(),
            dtype: DType::F32,
            store: WeightStore::F32,
            trainable: false,
            vars: RefCell::new(Vec::new()),
        }
    }

    /// Hand tensors out in `dtype` (f16/bf16 inference); default f32.
    pub fn with_dtype(mut self, dtype: DType) -> Self {
        // On the CPU the activations stay f32: bf16 multiplies weights packed once in bf16 (`nn::bf16`), f16
        // stores the weights in f16 and widens them for the f32 kernels.
        self.store = WeightStore::for_dtype(dtype, &self.device);
        self.dtype = if self.store == WeightStore::F32 { dtype } else { DType::F32 };
        self
    }

    /// How layers keep their products' weights (f32 for trainable weights).
    pub fn store(&self) -> WeightStore {
        if self.trainable {
            WeightStore::F32
        } else {
            self.store
        }
    }

    pub fn dtype(&self) -> DType {
        self.dtype
    }

    /// Hand every tensor out as a (copied) `Var`, so that a forward in the kernels' differentiable mode
    /// ([`crate::kernels::set_differentiable`]) gives the weights gradients; [`Self::take_vars`] lists them.
    pub fn trainable(mut self) -> Self {
        self.trainable = true;
        self
    }

    /// Whether tensors are handed out as `Var`s ([`Self::trainable`]).
    pub fn is_trainable(&self) -> bool {
        self.trainable
    }

    /// The `Var`s handed out so far in trainable mode, by model name.
    pub fn take_vars(&self) -> Vec<(String, Var)> {
        std::mem::take(&mut *self.vars.borrow_mut())
    }

    fn hand_out(&self, name: &str, t: Tensor) -> candle_core::Result<Tensor> {
        let t = if t.dtype() == self.dtype { t } else { t.to_dtype(self.dtype)? };
        if !self.trainable {
            return Ok(t);
        }
        let v = Var::from_tensor(&t)?;
        let out = v.as_tensor().clone();
        self.vars.borrow_mut().push((name.to_string(), v));
        Ok(out)
    }

    /// The tensors handed out so far in random mode, by model name (empty for file-backed weights).
    pub fn take_recorded(&self) -> Vec<(String, Tensor)> {
        std::mem::take(&mut *self.recorded.borrow_mut())
    }

    /// True when nothing in scope was found (wrong prefix / layout).
    pub fn is_empty(&self) -> bool {
        self.recipes.is_empty() && self.unexpected.is_empty()
    }

    /// Whether the file holds model tensor `name` (optional modules such as `quant_conv`).
    pub fn contains(&self, name: &str) -> bool {
        self.recipes.contains_key(name)
    }

    fn read(&self, key: &str) -> Result<Tensor, WeightsError> {
        let Some(st) = &self.st else {
            return Err(WeightsError::Open { path: self.path.clone(), msg: format!("no file to read `{key}` from") });
        };
        let t = st.load(key, &self.device).map_err(|source| WeightsError::Read { path: self.path.clone(), key: key.to_string(), source })?;
        // f16/bf16 checkpoints are upcast once at load time.
        if t.dtype() == DType::F32 {
            Ok(t)
        } else {
            t.to_dtype(DType::F32).map_err(|source| WeightsError::Read { path: self.path.clone(), key: key.to_string(), source })
        }
    }

    fn placeholder(&self, shape: &[usize]) -> candle_core::Result<Tensor> {
        Tensor::zeros(shape, self.dtype, &self.device)
    }

    /// Model tensor `name` with the expected `shape`, in [`Self::dtype`]. Missing / wrongly shaped tensors are recorded
    /// and replaced by zeros, so that [`Self::finish`] can list every problem at once.
    pub fn get(&self, name: &str, shape: &[usize]) -> candle_core::Result<Tensor> {
        if self.st.is_none() {
            let mut c = self.counter.borrow_mut();
            *c += 1;
            let t = random_tensor(name, shape, self.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15).wrapping_add(*c), &self.device)?;
            if self.store == WeightStore::F32 {
                // A packed model is never exported; keeping its f32 tensors would double the load's peak.
                self.recorded.borrow_mut().push((name.to_string(), t.clone()));
            }
            return self.hand_out(name, t);
        }
        let Some(recipe) = self.recipes.get(name) else {
            self.missing.borrow_mut().push(name.to_string());
            return self.placeholder(shape);
        };
        self.used.borrow_mut().insert(name.to_string());
        let wrap = |e: WeightsError| candle_core::Error::Msg(e.to_string());
        let t = match recipe.parts.as_slice() {
            [(_, key, piece)] if !matches!(piece, Piece::Concat { .. }) => {
                let t = self.read(key).map_err(wrap)?;
                match piece {
                    Piece::Whole => t,
                    Piece::Transpose if t.rank() == 2 => t.t()?.contiguous()?,
                    Piece::Reshape if t.elem_count() == shape.iter().product::<usize>() => t.reshape(shape)?,
                    _ => {
                        self.mismatched.borrow_mut().push(format!("{key}: stored {:?} cannot become {name} {shape:?}", t.dims()));
                        return self.placeholder(shape);
                    }
                }
            }
            parts => {
                let of = match parts.first() {
                    Some((_, _, Piece::Concat { of, .. })) => *of,
                    _ => 0,
                };
                let complete = parts.len() == of && parts.iter().enumerate().all(|(i, p)| p.0 == i && matches!(p.2, Piece::Concat { .. }));
                if !complete {
                    let have: Vec<&str> = parts.iter().map(|p| p.1.as_str()).collect();
                    self.missing.borrow_mut().push(format!("{name} (needs {of} concatenated parts, found {have:?})"));
                    return self.placeholder(shape);
                }
                let ts = parts.iter().map(|p| self.read(&p.1).map_err(wrap)).collect::<candle_core::Result<Vec<_>>>()?;
                Tensor::cat(&ts, 0)?
            }
        };
        if t.dims() != shape {
            self.mismatched.borrow_mut().push(format!("{name}: file {:?}, model {shape:?}", t.dims()));
            return self.placeholder(shape);
        }
        self.hand_out(name, t)
    }

    /// Strict check: any missing, unexpected or wrongly shaped key is one error listing all of them.
    pub fn finish(self) -> Result<(), WeightsError> {
        if self.st.is_none() {
            return Ok(());
        }
        let used = self.used.borrow();
        let mut unexpected = self.unexpected.clone();
        for (name, r) in &self.recipes {
            if !used.contains(name) {
                unexpected.extend(r.parts.iter().map(|p| p.1.clone()));
            }
        }
        unexpected.sort();
        let missing = self.missing.borrow().clone();
        let mismatched = self.mismatched.borrow().clone();
        if missing.is_empty() && unexpected.is_empty() && mismatched.is_empty() {
            return Ok(());
        }
        Err(WeightsError::KeyMismatch { path: self.path.clone(), what: self.what.clone(), missing, unexpected, mismatched })
    }
}

/// xorshift64* stream → uniform in [−scale, scale).
fn random_tensor(name: &str, shape: &[usize], seed: u64, device: &Device) -> candle_core::Result<Tensor> {
    if shape.len() <= 1 {
        let v = if name.ends_with(".weight") { 1.0 } else { 0.0 };
        return Tensor::full(v as f32, shape, device);
    }
    let fan_in: usize = shape[1..].iter().product();
    let scale = 1.0 / (fan_in.max(1) as f32).sqrt();
    let mut s = seed | 1;
    let data: Vec<f32> = (0..shape.iter().product::<usize>())
        .map(|_| {
            s ^= s >> 12;
            s ^= s << 25;
            s ^= s >> 27;
            let r = s.wrapping_mul(0x2545_F491_4F6C_DD1D);
            ((r >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * scale
        })
        .collect();
    Tensor::from_vec(data, shape, device)
}
