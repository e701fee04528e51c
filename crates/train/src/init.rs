//! Initial weights from a model folder or a weights file (safetensors, or an official `.ckpt`/`.pth`).
//!
//! Keys are matched by name (`encoder.*`). A tensor whose shape grew relative to the file (MVSplat →
//! MVSplat360: `to_gaussians` widens for the feature SH) is built as the official `fit_ckpt` does: zeros, with the
//! file's values in the leading slice. A tensor absent from the file keeps its initialisation and is reported.

use std::path::Path;

use candle_core::{DType, Tensor};
use candle_nn::VarMap;
use mvsplat360_encoder::Checkpoint;

use crate::error::{Result, TrainError};

#[derive(Debug, Default, Clone)]
pub struct InitReport {
    pub loaded: usize,
    pub grown: Vec<String>,
    pub missing: Vec<String>,
}

pub fn load_into(varmap: &VarMap, path: &Path) -> Result<InitReport> {
    let file = if path.is_dir() { path.join(mvsplat360_pipeline::model::MODEL_WEIGHTS) } else { path.to_path_buf() };
    let cerr = |msg: String| TrainError::Config { path: file.clone(), msg };
    let ck = Checkpoint::open(&file).map_err(|e| cerr(e.to_string()))?;
    let data = varmap.data().lock().map_err(|_| cerr("varmap poisoned".into()))?;
    let mut rep = InitReport::default();
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    for name in names {
        let var = &data[name];
        let Some(shape) = ck.shape(name).map(|s| s.to_vec()) else {
            rep.missing.push(name.clone());
            continue;
        };
        let t = ck.load(name, DType::F32, var.device()).map_err(|e| cerr(e.to_string()))?;
        let want = var.dims().to_vec();
        if shape == want {
            var.set(&t)?;
            rep.loaded += 1;
        } else if shape.len() == want.len() && shape.iter().zip(&want).all(|(a, b)| a <= b) {
            // Zero-pad the file's tensor up to the model's shape, one dimension at a time.
            let mut block = t;
            for (d, (&have, &full)) in shape.iter().zip(&want).enumerate() {
                if have < full {
                    let mut pad_dims = block.dims().to_vec();
                    pad_dims[d] = full - have;
                    let pad = Tensor::zeros(pad_dims, DType::F32, var.device())?;
                    block = Tensor::cat(&[&block, &pad], d)?;
                }
            }
            var.set(&block)?;
            rep.grown.push(format!("{name} {shape:?}→{want:?}"));
        } else {
            return Err(cerr(format!("`{name}`: file shape {shape:?} cannot initialise the model's {want:?}")));
        }
    }
    if rep.loaded == 0 && rep.grown.is_empty() {
        return Err(cerr("no tensor of the model (keys `encoder.*`) is in this file".into()));
    }
    Ok(rep)
}
