//! Parity with the official VGGT (44b3afb) on golden fixtures made by `scripts/fixtures/official_vggt.py`
//! from the official modules (a reduced config; see tests/fixtures/model/README.md): patch tokens, the
//! interpolated positional embedding, aggregated tokens of several blocks, every camera-head iteration, depth,
//! points, their confidences and the cameras.
//!
//! Error model: each case file records, per tensor, the official f32 run's max |f32 − f64| (`f64_maxabs`,
//! the same model and inputs in float64). Ours is another f32 evaluation of the same maths, so it is expected
//! within a small multiple of that from the f32 reference: bound = 8 · f64_maxabs + 4 u · max|ref| (u = 2⁻²³,
//! the floor for tensors computed exactly). Every check also proves it is not vacuous (testkit: 1 % of the
//! entries moved by 3× their bound must fail), fails on the reference scaled by 1.01, and the mutations below
//! (first-frame tokens swapped, RoPE axes swapped, antialias off) must fail it.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use mvsplat360_testkit::{check, to_f64, Tol};
use mvsplat360_vggt::layers::rope::{frame_positions, RopeTables};
use mvsplat360_vggt::layers::vision_transformer::interpolate_bicubic_aa;
use mvsplat360_vggt::utils::pose_enc::pose_encoding_to_extri_intri;
use mvsplat360_vggt::weights;
use mvsplat360_vggt::{Vggt, VggtConfig};

const U: f64 = 1.0 / (1u64 << 23) as f64;
/// Error of a float32 antialiased bicubic resize, in units of u × max|input|: each of the two passes sums
/// ≤ 4·max(scale, 1) + 1 taps (≤ 7 for VGGT's grids) whose |weights| sum to ≤ 1.25 (Keys' a = −0.5 lobes),
/// each product and partial sum rounded once, and PyTorch rounds the first pass to f32 too: 2 · (7 + 7 + 2) ·
/// 1.25 = 40.
const INTERP_U: f64 = 40.0;

fn fixture_dir() -> PathBuf {
    let d = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/model");
    assert!(d.is_dir(), "VGGT fixtures missing at {} (made by scripts/fixtures/official_vggt.py)", d.display());
    d
}

fn metadata(path: &Path) -> HashMap<String, String> {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let (_, meta) = safetensors::SafeTensors::read_metadata(&bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    meta.metadata().clone().unwrap_or_default()
}

struct Case {
    name: String,
    t: HashMap<String, Tensor>,
    maxabs: HashMap<String, f64>,
}

impl Case {
    fn get(&self, k: &str) -> &Tensor {
        self.t.get(k).unwrap_or_else(|| panic!("{}: no tensor `{k}`", self.name))
    }

    fn tol(&self, k: &str) -> Tol {
        let e = self.get(k);
        let max_ref = to_f64(e).iter().fold(0f64, |m, v| m.max(v.abs()));
        let err = *self.maxabs.get(k).unwrap_or_else(|| panic!("{}: no f64_maxabs for `{k}`", self.name));
        // The official interpolation runs in float32 whatever the model's dtype, so the f64 run cannot show its
        // rounding: that tensor takes the interpolation's own model (see `interp_bound`).
        let floor = if k == "pos_embed" { INTERP_U * U } else { 4.0 * U };
        Tol::of_max((8.0 * err + floor * max_ref) / max_ref.max(f64::MIN_POSITIVE))
    }

    /// The comparison's failure, if any; also asserts the reference × 1.01 fails it.
    fn compare(&self, k: &str, actual: &Tensor) -> Option<String> {
        let e = self.get(k);
        let actual = actual.to_dtype(DType::F32).unwrap().reshape(e.dims()).unwrap();
        let tol = self.tol(k);
        let scaled = (e * 1.01).unwrap();
        assert!(
            check(&format!("{}/{k} vs ref×1.01", self.name), &actual, &scaled, tol).is_some(),
            "{}/{k}: the tolerance accepts the reference scaled by 1.01",
            self.name
        );
        check(&format!("{}/{k}", self.name), &actual, e, tol)
    }
}

fn cases(seed: u32) -> Vec<Case> {
    let dir = fixture_dir();
    let mut out = Vec::new();
    let mut names: Vec<PathBuf> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).collect();
    names.sort();
    for p in names {
        let n = p.file_name().unwrap().to_string_lossy().to_string();
        if !n.starts_with(&format!("case_seed{seed}_")) {
            continue;
        }
        let meta = metadata(&p);
        let maxabs: HashMap<String, f64> = serde_json::from_str(meta.get("f64_maxabs").expect("f64_maxabs")).unwrap();
        out.push(Case { name: n, t: candle_core::safetensors::load(&p, &Device::Cpu).unwrap(), maxabs });
    }
    assert!(!out.is_empty(), "no case files for seed {seed} in {}", dir.display());
    out
}

/// The model through the product's loader: a model folder (config.json + model.safetensors) made from the
/// fixture's weights, loaded strictly.
fn load_model(seed: u32) -> (Vggt, VggtConfig, tempfile::TempDir, HashMap<String, Tensor>) {
    let w = fixture_dir().join(format!("weights_seed{seed}.safetensors"));
    let cfg_json = metadata(&w).remove("config").expect("config in metadata");
    let cfg: VggtConfig = serde_json::from_str(&cfg_json).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    std::fs::write(tmp.path().join("config.json"), &cfg_json).unwrap();
    std::fs::copy(&w, tmp.path().join("model.safetensors")).unwrap();
    let (model, report) = weights::load(tmp.path(), &Device::Cpu).unwrap();
    assert!(report.skipped.is_empty());
    let tensors = candle_core::safetensors::load(&w, &Device::Cpu).unwrap();
    (model, cfg, tmp, tensors)
}

fn run_case(model: &Vggt, cfg: &VggtConfig, case: &Case) -> Vec<String> {
    let mut fails = Vec::new();
    let images = case.get("images");
    let (s, _, h, w) = images.dims4().unwrap();
    let last = cfg.depth - 1;
    let pred = model.forward(images, &[0, 1, last]).unwrap();
    let mut cmp = |k: &str, t: &Tensor| {
        if let Some(f) = case.compare(k, t) {
            fails.push(f);
        }
    };
    cmp("patch_tokens", &model.aggregator.patch_tokens(images).unwrap());
    cmp("pos_embed", &model.aggregator.patch_embed.interpolate_pos_encoding(h, w).unwrap());
    for (i, t) in &pred.tokens {
        cmp(&format!("tokens.{i}"), t);
    }
    for (i, t) in pred.pose_enc_list.iter().enumerate() {
        cmp(&format!("pose_enc.{i}"), t);
    }
    let (d, dc) = pred.depth.as_ref().unwrap();
    cmp("depth", d);
    cmp("depth_conf", dc);
    let (p, pc) = pred.world_points.as_ref().unwrap();
    cmp("world_points", p);
    cmp("world_points_conf", pc);
    // Cameras from our encoding, compared with the official conversion of the official encoding.
    let enc = pred.pose_enc().unwrap().to_vec2::<f32>().unwrap();
    let mut ext = Vec::new();
    let mut int = Vec::new();
    for e in &enc {
        let cam = pose_encoding_to_extri_intri(&e[..].try_into().unwrap(), h, w);
        ext.extend(cam.extrinsic.iter().flatten().map(|&v| v as f32));
        int.extend(cam.intrinsic.iter().flatten().map(|&v| v as f32));
    }
    cmp("extrinsics", &Tensor::from_vec(ext, (s, 3, 4), &Device::Cpu).unwrap());
    cmp("intrinsics", &Tensor::from_vec(int, (s, 3, 3), &Device::Cpu).unwrap());
    fails
}

#[test]
fn matches_official_seed0() {
    let (model, cfg, _tmp, _) = load_model(0);
    let fails: Vec<String> = cases(0).iter().flat_map(|c| run_case(&model, &cfg, c)).collect();
    assert!(fails.is_empty(), "{}", fails.join("\n"));
}

#[test]
fn matches_official_seed1() {
    let (model, cfg, _tmp, _) = load_model(1);
    let fails: Vec<String> = cases(1).iter().flat_map(|c| run_case(&model, &cfg, c)).collect();
    assert!(fails.is_empty(), "{}", fails.join("\n"));
}

/// Swapping the first frame's camera and register tokens with the others' must break the parity.
#[test]
fn mutation_first_frame_tokens_swapped_fails() {
    let (_, cfg, _tmp, mut tensors) = load_model(0);
    for k in ["aggregator.camera_token", "aggregator.register_token"] {
        let t = tensors[k].clone();
        let swapped = Tensor::cat(&[&t.narrow(1, 1, 1).unwrap(), &t.narrow(1, 0, 1).unwrap()], 1).unwrap();
        tensors.insert(k.into(), swapped);
    }
    let model = weights::from_tensors(tensors, &cfg, &Device::Cpu, DType::F32).unwrap();
    for case in cases(0) {
        let pred = model.forward(case.get("images"), &[]).unwrap();
        assert!(case.compare("pose_enc.3", pred.pose_enc().unwrap()).is_some(), "{}: swapped first-frame tokens still pass", case.name);
        assert!(case.compare("depth", &pred.depth.as_ref().unwrap().0).is_some(), "{}: swapped first-frame tokens still pass (depth)", case.name);
    }
}

/// The first aggregated block with RoPE's axes swapped (x rotating the first half, y the second) must fail
/// on `tokens.0`, where the same loop with the right axes passes.
#[test]
fn mutation_rope_axes_swapped_fails() {
    let (model, cfg, _tmp, _) = load_model(0);
    for case in cases(0) {
        let images = case.get("images");
        let (s, _, h, w) = images.dims4().unwrap();
        let agg = &model.aggregator;
        let first_tokens = |swap: bool| -> Tensor {
            let patch = agg.patch_tokens(images).unwrap();
            let pick = |t: &Tensor, i: usize| t.narrow(1, i, 1).unwrap().squeeze(1).unwrap();
            let sp = |i: usize| Tensor::cat(&[&pick(&agg.camera_token, i), &pick(&agg.register_token, i)], 1).unwrap();
            let others = sp(1).broadcast_as((s - 1, cfg.patch_start_idx(), cfg.embed_dim)).unwrap();
            let special = Tensor::cat(&[&sp(0), &others], 0).unwrap();
            let tokens = Tensor::cat(&[&special, &patch], 1).unwrap();
            let (_, n, c) = tokens.dims3().unwrap();
            let mut pos = frame_positions(cfg.patch_start_idx(), h / cfg.patch_size, w / cfg.patch_size);
            if swap {
                pos.iter_mut().for_each(|p| *p = (p.1, p.0));
            }
            let all: Vec<(u32, u32)> = (0..s).flat_map(|_| pos.iter().copied()).collect();
            let hd = c / cfg.num_heads;
            let fr = RopeTables::new(&pos, hd, cfg.rope_freq, &Device::Cpu).unwrap();
            let gr = RopeTables::new(&all, hd, cfg.rope_freq, &Device::Cpu).unwrap();
            let f = agg.frame_blocks[0].forward(&tokens, Some(&fr)).unwrap();
            let g = agg.global_blocks[0].forward(&f.reshape((1, s * n, c)).unwrap(), Some(&gr)).unwrap().reshape((s, n, c)).unwrap();
            Tensor::cat(&[&f, &g], 2).unwrap()
        };
        assert!(case.compare("tokens.0", &first_tokens(false)).is_none(), "{}: the hand-run first block does not match", case.name);
        assert!(case.compare("tokens.0", &first_tokens(true)).is_some(), "{}: RoPE with swapped axes still passes", case.name);
    }
}

/// The antialiased bicubic resize of the positional embedding at VGGT-1B's grid (37 × 37) to the grids of
/// real inputs, against PyTorch's; PyTorch's non-antialiased result must fail the same check.
#[test]
fn pos_embed_interpolation_antialias() {
    let p = fixture_dir().join("pos_embed_interp.safetensors");
    let t = candle_core::safetensors::load(&p, &Device::Cpu).unwrap();
    // (1, M², C) tokens, as the patch part of a positional embedding.
    let grid = &t["grid"];
    let (mm, c) = (grid.dim(1).unwrap(), grid.dim(2).unwrap());
    let m = (mm as f64).sqrt() as usize;
    assert_eq!(m * m, mm);
    let planes = grid.reshape((mm, c)).unwrap().t().unwrap().contiguous().unwrap().to_vec2::<f32>().unwrap();
    let mut checked = 0;
    for (name, want) in &t {
        let Some(size) = name.strip_prefix("aa.") else { continue };
        let (h, w) = size.split_once('x').map(|(a, b)| (a.parse::<usize>().unwrap(), b.parse::<usize>().unwrap())).unwrap();
        let ours: Vec<f32> = planes.iter().flat_map(|pl| interpolate_bicubic_aa(pl, m, m, h, w)).collect();
        let ours = Tensor::from_vec(ours, (1, c, h, w), &Device::Cpu).unwrap();
        let max_in = planes.iter().flatten().fold(0f64, |m, v| m.max(v.abs() as f64));
        let tol = Tol::abs(INTERP_U * U * max_in);
        if let Some(f) = check(name, &ours, want, tol) {
            panic!("{f}");
        }
        if size == "21x37" {
            assert!(check("noaa", &ours, &t["noaa.21x37"], tol).is_some(), "antialias off still passes");
        }
        checked += 1;
    }
    assert!(checked >= 4, "only {checked} antialiased sizes in the fixture");
}

/// The bf16 trunk's outputs on the seed-0 fixtures against the official f32 outputs (which the f32 model
/// matches to f32 precision): the RMS error of each output within 0.05 × the reference's RMS. Returns the
/// outputs, case by case.
fn bf16_within_bound(model: &Vggt, label: &str) -> Vec<Vec<f64>> {
    let mut outs = Vec::new();
    for case in cases(0) {
        let pred = model.forward(case.get("images"), &[]).unwrap();
        let d = &pred.depth.as_ref().unwrap().0;
        assert_eq!(d.dtype(), DType::F32, "heads run in f32");
        for (k, t) in [("pose_enc.3", pred.pose_enc().unwrap()), ("depth", d), ("world_points", &pred.world_points.as_ref().unwrap().0)] {
            let e = case.get(k);
            let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt();
            let a = to_f64(&t.reshape(e.dims()).unwrap());
            let r = to_f64(e);
            let err: Vec<f64> = a.iter().zip(&r).map(|(x, y)| x - y).collect();
            let (re, rr) = (rms(&err), rms(&r));
            eprintln!("{label}: {}/{k}: rms err {re:.3e}, rms ref {rr:.3e}, ratio {:.3e}", case.name, re / rr);
            assert!(re <= 0.05 * rr, "{label}: {}/{k}: bf16 trunk rms error {re:.3e} over 0.05 × rms ref {rr:.3e}", case.name);
            outs.push(a);
        }
    }
    outs
}

/// The bf16 trunk (upstream's autocast) on the CPU: with AVX512-BF16 the blocks' linears (attention qkv/proj,
/// MLP fc1/fc2) run in `nn`'s packed bf16 product and everything else in f32 (attention's products would run in
/// bf16 too for heads of 64; the fixtures' heads of 8 keep them f32: `layers::attention`'s test covers that wiring),
/// and so do the DPT heads' products (bf16 Winograd, packed convs and linears; their activations f32); without
/// it, candle's bf16 ops with the aggregator's weights and tokens in bf16 and the heads in f32. bf16 keeps 8 significant
/// bits (u = 2⁻⁸); each block rounds its products' operands (and, through candle, its outputs), and ~10 blocks
/// compound that, so the outputs are compared by their RMS error against 0.05 × the reference's RMS (≈ 13 u):
/// a wrong cast, a head left in bf16 or a token taken from the wrong place gives O(1) errors.
#[test]
fn bf16_trunk_within_bf16_error() {
    let (_, cfg, _tmp, tensors) = load_model(0);
    let model = weights::from_tensors(tensors, &cfg, &Device::Cpu, DType::BF16).unwrap();
    assert_eq!(model.depth_head.as_ref().unwrap().norm.weight.dtype(), DType::F32);
    let packed = mvsplat360_nn::bf16::hardware_dpbf16();
    assert_eq!(model.aggregator.bf16_packed(), packed, "the linears are packed exactly when the CPU has AVX512-BF16");
    if packed {
        assert_eq!(model.aggregator.camera_token.dtype(), DType::F32, "tokens stay f32 with packed linears");
        assert!(model.aggregator.patch_embed.blocks[0].mlp.fc2.packed.is_some(), "DINOv2's blocks are packed too");
        let qkv = &model.aggregator.frame_blocks[0].attn.qkv;
        assert_eq!(qkv.weight.elem_count(), 0, "no weight tensor kept beside the packed copy");
        assert!(model.depth_head.as_ref().unwrap().bf16_packed() && model.point_head.as_ref().unwrap().bf16_packed(), "the heads' products in bf16");
    } else {
        assert_eq!(model.aggregator.frame_blocks[0].attn.qkv.weight.dtype(), DType::BF16);
    }
    bf16_within_bound(&model, if packed { "packed bf16 linears" } else { "candle bf16" });
}

/// AVX512-BF16 masked ([`mvsplat360_nn::bf16::with_bf16_masked`], which masks the calling thread only): a
/// model loaded under the mask falls back to candle's bf16 trunk; a packed model run under the mask takes the
/// storage-only product (bf16 weights widened, f32 activations). The mask reaches that dispatch because the
/// aggregator calls its linears in sequence on the calling thread (rayon's workers only split each product,
/// after `nn::bf16::path` has been read). Both within the bound; the storage-only outputs differ from the
/// `vdpbf16ps` ones (unrounded activations), which shows the mask took effect. On a CPU without the feature
/// only the first half runs.
#[test]
fn bf16_trunk_masked_falls_back() {
    let (_, cfg, _tmp, tensors) = load_model(0);
    let candle = mvsplat360_nn::bf16::with_bf16_masked(|| weights::from_tensors(tensors.clone(), &cfg, &Device::Cpu, DType::BF16)).unwrap();
    assert!(!candle.aggregator.bf16_packed(), "masked at load: candle's bf16 trunk");
    assert_eq!(candle.aggregator.camera_token.dtype(), DType::BF16);
    bf16_within_bound(&candle, "candle bf16 (masked at load)");
    if !mvsplat360_nn::bf16::hardware_dpbf16() {
        eprintln!("no AVX512-BF16 on this CPU: the packed model's masked run is not tested");
        return;
    }
    let model = weights::from_tensors(tensors, &cfg, &Device::Cpu, DType::BF16).unwrap();
    assert!(model.aggregator.bf16_packed());
    let dp = bf16_within_bound(&model, "packed, vdpbf16ps");
    let so = mvsplat360_nn::bf16::with_bf16_masked(|| bf16_within_bound(&model, "packed, storage-only (masked)"));
    assert_ne!(dp, so, "the masked run took the same path as the unmasked one");
}
