//! Strict, mmapped UNet weight source in sgm key names (any stored layout goes through one name map),
//! or seeded random weights for benchmarks.

use std::cell::RefCell;
use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};

use candle_core::safetensors::MmapedSafetensors;
use candle_core::{DType, Device, Result, Tensor, Var};
use rayon::prelude::*;

use super::util::WeightStore;
use super::{UNetError, VideoUNetConfig};
use crate::unet::keymap::diffusers_to_sgm;

/// How the UNet keys are spelled in a file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum UNetLayout {
    /// sgm names under a prefix: `model.diffusion_model.` (svd.safetensors),
    /// `refiner.model.diffusion_model.` (MVSplat360 checkpoint) or `` (bare state dict).
    Sgm { prefix: String },
    /// diffusers `UNetSpatioTemporalConditionModel` names.
    Diffusers,
}

impl UNetLayout {
    /// Detect the layout from the key names.
    pub fn detect<'a>(keys: impl Iterator<Item = &'a str> + Clone) -> Option<Self> {
        for prefix in ["refiner.model.diffusion_model.", "model.diffusion_model."] {
            if keys.clone().any(|k| k.starts_with(prefix)) {
                return Some(Self::Sgm { prefix: prefix.to_string() });
            }
        }
        if keys.clone().any(|k| k == "input_blocks.0.0.weight") {
            return Some(Self::Sgm { prefix: String::new() });
        }
        if keys.clone().any(|k| k == "conv_in.weight") {
            return Some(Self::Diffusers);
        }
        None
    }
}

enum Source {
    File { st: MmapedSafetensors, path: PathBuf, map: HashMap<String, String> },
    Random { seed: u64 },
}

/// Hands out tensors by sgm name, recording missing/mismatched/used keys for a strict final check.
pub struct Weights {
    src: Source,
    device: Device,
    /// dtype tensors are handed out in (f32 unless [`Weights::with_dtype`]).
    dtype: DType,
    /// How the layers keep their products' weights (CPU bf16/f16: handed out in f32, see [`Self::store`]).
    store: WeightStore,
    used: RefCell<BTreeSet<String>>,
    missing: RefCell<Vec<String>>,
    mismatched: RefCell<Vec<String>>,
    unexpected: Vec<String>,
    counter: RefCell<u64>,
    /// Random mode: every tensor handed out, by sgm name (to save a random model as a state dict).
    recorded: RefCell<Vec<(String, Tensor)>>,
    /// Trainable mode: every tensor is handed out as a `Var` (listed here by sgm name).
    trainable: bool,
    vars: RefCell<Vec<(String, Var)>>,
}

impl Weights {
    /// Open a safetensors file (mmapped) and map its UNet keys to sgm names.
    pub fn from_file(path: &Path, layout: Option<UNetLayout>, cfg: &VideoUNetConfig, device: &Device) -> std::result::Result<Self, UNetError> {
        // SAFETY: the file is opened read-only; mutating it while mapped is the caller's problem, as in candle.
        let st = unsafe { MmapedSafetensors::new(path) }.map_err(|e| UNetError::Open { path: path.to_path_buf(), msg: e.to_string() })?;
        let names: Vec<String> = st.tensors().into_iter().map(|(n, _)| n).collect();
        let layout = match layout {
            Some(l) => l,
            None => UNetLayout::detect(names.iter().map(|s| s.as_str())).ok_or_else(|| UNetError::UnknownLayout { path: path.to_path_buf() })?,
        };
        let mut map = HashMap::new();
        let mut unexpected = Vec::new();
        match &layout {
            UNetLayout::Sgm { prefix } => {
                for n in &names {
                    if let Some(rest) = n.strip_prefix(prefix.as_str()) {
                        map.insert(rest.to_string(), n.clone());
                    }
                }
            }
            UNetLayout::Diffusers => {
                for n in &names {
                    match diffusers_to_sgm(n, cfg) {
                        Some(s) => {
                            map.insert(s, n.clone());
                        }
                        None => unexpected.push(n.clone()),
                    }
                }
            }
        }
        if map.is_empty() {
            return Err(UNetError::UnknownLayout { path: path.to_path_buf() });
        }
        Ok(Self::new(Source::File { st, path: path.to_path_buf(), map }, device, unexpected))
    }

    /// Seeded random weights (benchmarks): uniform ±1/√fan_in for matrices/kernels, 1 for norm scales,
    /// 0 for biases and mix factors.
    pub fn random(seed: u64, device: &Device) -> Self {
        Self::new(Source::Random { seed }, device, Vec::new())
    }

    fn new(src: Source, device: &Device, unexpected: Vec<String>) -> Self {
        Self {
            src,
            device: device.clone(),
            dtype: DType::F32,
            store: WeightStore::F32,
            used: RefCell::new(BTreeSet::new()),
            missing: RefCell::new(Vec::new()),
            mismatched: RefCell::new(Vec::new()),
            unexpected,
            counter: RefCell::new(0),
            recorded: RefCell::new(Vec::new()),
            trainable: false,
            vars: RefCell::new(Vec::new()),
        }
    }

    /// Hand every tensor out as a (copied) `Var`, so that a forward in the kernels' differentiable mode
    /// ([`crate::kernels::set_differentiable`]) gives the weights gradients; [`Self::take_vars`] lists them.
    /// Costs one copy of the weights; the model rearranges its temporal-conv weights at every call then.
    pub fn trainable(mut self) -> Self {
        self.trainable = true;
        self
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

    pub fn is_trainable(&self) -> bool {
        self.trainable
    }

    /// The `Var`s handed out so far in trainable mode, by sgm name.
    pub fn take_vars(&self) -> Vec<(String, Var)> {
        std::mem::take(&mut *self.vars.borrow_mut())
    }

    fn hand_out(&self, name: &str, t: Tensor) -> Result<Tensor> {
        let t = if t.dtype() == self.dtype { t } else { t.to_dtype(self.dtype)? };
        if !self.trainable {
            return Ok(t);
        }
        let v = Var::from_tensor(&t)?;
        let out = v.as_tensor().clone();
        self.vars.borrow_mut().push((name.to_string(), v));
        Ok(out)
    }

    /// Tensor `name` (sgm name, no prefix) in [`Self::dtype`] with the expected shape. Missing or wrongly shaped
    /// tensors are recorded (reported together by [`Weights::finish`]) and replaced by a zero view.
    pub fn get(&self, name: &str, shape: &[usize]) -> Result<Tensor> {
        match &self.src {
            Source::Random { seed } => {
                let mut c = self.counter.borrow_mut();
                *c += 1;
                let t = random_tensor(name, shape, seed.wrapping_mul(0x9E37_79B9_7F4A_7C15).wrapping_add(*c), &self.device)?;
                if self.store == WeightStore::F32 {
                    // A packed model is never exported; keeping its f32 tensors would double the load's peak.
                    self.recorded.borrow_mut().push((name.to_string(), t.clone()));
                }
                self.hand_out(name, t)
            }
            Source::File { st, map, .. } => {
                let Some(stored) = map.get(name) else {
                    self.missing.borrow_mut().push(name.to_string());
                    return Tensor::zeros(1, self.dtype, &self.device)?.reshape(vec![1; shape.len()])?.broadcast_as(shape);
                };
                self.used.borrow_mut().insert(name.to_string());
                let mut t = st.load(stored, &self.device)?;
                // Stability's svd.safetensors feeds label_emb with fps/motion/cond_aug (768 inputs);
                // MVSplat360 keeps only the first 256 columns (the cond_aug embedding).
                if name == "label_emb.0.0.weight" && t.rank() == 2 && shape.len() == 2 && t.dim(1)? > shape[1] && t.dim(0)? == shape[0] {
                    t = t.narrow(1, 0, shape[1])?.contiguous()?;
                }
                if t.dims() != shape {
                    self.mismatched.borrow_mut().push(format!("{stored}: file {:?}, model {:?}", t.dims(), shape));
                    return Tensor::zeros(1, self.dtype, &self.device)?.reshape(vec![1; shape.len()])?.broadcast_as(shape);
                }
                if t.dtype() != DType::F32 {
                    t = t.to_dtype(DType::F32)?;
                }
                self.hand_out(name, t)
            }
        }
    }

    /// The tensors handed out so far in random mode, by sgm name (empty for file-backed weights).
    pub fn take_recorded(&self) -> Vec<(String, Tensor)> {
        std::mem::take(&mut *self.recorded.borrow_mut())
    }

    /// Strict check: any missing, unexpected or wrongly shaped key is an error listing all of them.
    pub fn finish(self) -> std::result::Result<(), UNetError> {
        let Source::File { map, path, .. } = &self.src else { return Ok(()) };
        let used = self.used.borrow();
        let mut unexpected: Vec<String> = self.unexpected.clone();
        unexpected.extend(map.iter().filter(|(k, _)| !used.contains(*k)).map(|(_, v)| v.clone()));
        unexpected.sort();
        let missing = self.missing.borrow().clone();
        let mismatched = self.mismatched.borrow().clone();
        if missing.is_empty() && unexpected.is_empty() && mismatched.is_empty() {
            return Ok(());
        }
        Err(UNetError::KeyMismatch { path: path.clone(), missing, unexpected, mismatched })
    }
}

/// xorshift64* stream → uniform in [-1, 1).
fn fill_uniform(buf: &mut [f32], seed: u64, scale: f32) {
    let mut s = seed | 1;
    for v in buf.iter_mut() {
        s ^= s >> 12;
        s ^= s << 25;
        s ^= s >> 27;
        let r = s.wrapping_mul(0x2545_F491_4F6C_DD1D);
        *v = ((r >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * scale;
    }
}

fn random_tensor(name: &str, shape: &[usize], seed: u64, device: &Device) -> Result<Tensor> {
    let numel: usize = shape.iter().product();
    if shape.len() <= 1 {
        let v: f32 = if name.ends_with(".weight") { 1.0 } else { 0.0 };
        return Tensor::full(v, shape, device);
    }
    let fan_in: usize = shape[1..].iter().product();
    let scale = 1.0 / (fan_in as f32).sqrt();
    let mut data = vec![0f32; numel];
    const CHUNK: usize = 1 << 16;
    data.par_chunks_mut(CHUNK).enumerate().for_each(|(i, c)| fill_uniform(c, seed ^ (i as u64).wrapping_mul(0xD1B5_4A32_D192_ED03), scale));
    Tensor::from_vec(data, shape, device)
}
