//! Parity of the OpenCLIP image embedder (open_clip-layout model, loaded from the transformers-layout fixture
//! through `keymap::clip`, and from the same weights re-keyed into the official layout) against
//! `svd/svd_pipeline.safetensors` (see svd/README.md). Tolerance: |Δ| ≤ 1e-5 × max|ref| of the tensor (scale-
//! relative; measured on 7 fixtures — shared + seeds 0–2 at two sizes — ≤ 8e-7 of max for the preprocessing and
//! ≤ 2.3e-7 for the embeddings and their mean: a 10× margin kept because the CLIP towers of real checkpoints are
//! 32 layers deep, not 2).

use std::collections::HashMap;
use std::path::PathBuf;

use candle_core::{DType, Device, Tensor};
use mvsplat360_refiner::clip::{clip_preprocess, ClipError, ClipImageEmbedder, ClipLayout, ClipVisionConfig};
use mvsplat360_refiner::keymap::clip::transformers_to_open_clip;
use mvsplat360_refiner::weights::Piece;
use mvsplat360_testkit::{self as tk, fixture, get, load, max_abs_diff, Tol};

fn cfg() -> ClipVisionConfig {
    ClipVisionConfig::from_transformers_json(&fixture("svd/svd_clip_vision_config.json")).expect("clip config")
}

fn embedder() -> ClipImageEmbedder {
    ClipImageEmbedder::load(&fixture("svd/svd_clip_vision.safetensors"), None, &cfg(), &Device::Cpu).expect("load transformers-layout clip")
}

fn flat_views(t: &Tensor) -> Tensor {
    let (b, v, c, h, w) = t.dims5().unwrap();
    t.reshape((b * v, c, h, w)).unwrap()
}

fn report(name: &str, a: &Tensor, e: &Tensor, tol: f64) {
    tk::assert_check(name, a, e, Tol::of_max(tol));
}

fn temp_file(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("mvsplat360_clip_{tag}_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join("w.safetensors")
}

#[test]
fn preprocessing_matches_clip_pixel_values() {
    let p = load("svd/svd_pipeline.safetensors");
    let px = clip_preprocess(&flat_views(get(&p, "context_views")), cfg().image_size).unwrap();
    report("clip_pixel_values", &px, get(&p, "clip_pixel_values"), 1e-5);
}

#[test]
fn embeddings_and_view_mean_match_fixture() {
    let p = load("svd/svd_pipeline.safetensors");
    let e = embedder();
    let from_px = e.embed_pixels(get(&p, "clip_pixel_values")).unwrap();
    report("clip_image_embeds (from fixture pixels)", &from_px, get(&p, "clip_image_embeds"), 1e-5);
    let from_views = e.embed(&flat_views(get(&p, "context_views"))).unwrap();
    report("clip_image_embeds (from views)", &from_views, get(&p, "clip_image_embeds"), 1e-5);
    let mean = e.embed_mean(get(&p, "context_views")).unwrap();
    report("clip_embedding", &mean, get(&p, "clip_embedding"), 1e-5);
}

/// Fixture weights rounded through f16: a transformers-layout f32 file and an official-layout
/// (`refiner.conditioner.embedders.0.open_clip.model.visual.*`, fused in_proj, proj = projectionᵀ) f16 file
/// with keys of other components must give the same embeddings.
#[test]
fn open_clip_layout_f16_checkpoint_loads_to_the_same_model() {
    let src = load("svd/svd_clip_vision.safetensors");
    let rounded: HashMap<String, Tensor> = src.iter().map(|(k, t)| (k.clone(), t.to_dtype(DType::F16).unwrap().to_dtype(DType::F32).unwrap())).collect();
    let mut parts: HashMap<String, Vec<(usize, Tensor)>> = HashMap::new();
    let mut official: HashMap<String, Tensor> = HashMap::new();
    let prefix = "refiner.conditioner.embedders.0.open_clip.model.visual.";
    for (k, t) in &rounded {
        let Some((name, piece)) = transformers_to_open_clip(k).unwrap_or_else(|| panic!("unmapped fixture key {k}")) else { continue };
        match piece {
            Piece::Concat { index, .. } => parts.entry(name).or_default().push((index, t.clone())),
            Piece::Transpose => {
                official.insert(format!("{prefix}{name}"), t.t().unwrap().contiguous().unwrap());
            }
            _ => {
                official.insert(format!("{prefix}{name}"), t.clone());
            }
        }
    }
    for (name, mut ps) in parts {
        ps.sort_by_key(|p| p.0);
        let ts: Vec<Tensor> = ps.into_iter().map(|p| p.1).collect();
        official.insert(format!("{prefix}{name}"), Tensor::cat(&ts, 0).unwrap());
    }
    let mut official: HashMap<String, Tensor> = official.into_iter().map(|(k, t)| (k, t.to_dtype(DType::F16).unwrap())).collect();
    // Other components of a full checkpoint: the text-tower leftovers and the VAE are not CLIP-vision keys.
    official.insert("refiner.conditioner.embedders.0.open_clip.model.ln_final.weight".into(), Tensor::ones(4, DType::F16, &Device::Cpu).unwrap());
    official.insert("refiner.first_stage_model.encoder.conv_in.bias".into(), Tensor::ones(4, DType::F16, &Device::Cpu).unwrap());
    let keys: Vec<String> = official.keys().cloned().collect();
    assert_eq!(ClipLayout::detect(&keys), Some(ClipLayout::OpenClip { prefix: prefix.into() }));

    let off_path = temp_file("official");
    candle_core::safetensors::save(&official, &off_path).unwrap();
    let tf_path = temp_file("rounded");
    candle_core::safetensors::save(&rounded, &tf_path).unwrap();
    let a = ClipImageEmbedder::load(&off_path, None, &cfg(), &Device::Cpu).expect("load official layout");
    let b = ClipImageEmbedder::load(&tf_path, None, &cfg(), &Device::Cpu).unwrap();
    let p = load("svd/svd_pipeline.safetensors");
    let px = get(&p, "clip_pixel_values");
    let (d, _) = max_abs_diff(&a.embed_pixels(px).unwrap(), &b.embed_pixels(px).unwrap());
    assert!(d <= 1e-6, "official (f16) vs transformers layout: {d:.3e}");
    for path in [off_path, tf_path] {
        let _ = std::fs::remove_dir_all(path.parent().unwrap());
    }
}

#[test]
fn strict_loading_lists_missing_and_unexpected_keys() {
    let mut src = load("svd/svd_clip_vision.safetensors");
    src.remove("vision_model.encoder.layers.1.self_attn.k_proj.weight").unwrap();
    src.insert("vision_model.encoder.layers.0.self_attn.qkv.weight".into(), Tensor::zeros(3, DType::F32, &Device::Cpu).unwrap());
    let path = temp_file("strict");
    candle_core::safetensors::save(&src, &path).unwrap();
    let err = ClipImageEmbedder::load(&path, None, &cfg(), &Device::Cpu).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, ClipError::Weights(_)), "{msg}");
    assert!(msg.contains("transformer.resblocks.1.attn.in_proj_weight"), "{msg}");
    assert!(msg.contains("vision_model.encoder.layers.0.self_attn.qkv.weight"), "{msg}");
    let _ = std::fs::remove_dir_all(path.parent().unwrap());
}
