//! `mvsplat360 bench vggt`: one forward of VGGT (aggregator, camera, depth and point heads) with seeded random
//! weights at the configured shape (VGGT-1B by default) on synthetic frames: median time, peak memory, and the
//! multiply-adds counted from the shapes (so the line also gives the achieved GFLOP/s). With MVSPLAT360_PROFILE=1
//! the line also has `profile`: totals per part (DINOv2, frame blocks, global blocks, heads) over the timed runs.

use std::time::Instant;

use candle_core::{Device, Tensor};
use mvsplat360_nn::bench::{median, peak_rss_mib};
use serde_json::json;

use crate::config::VggtConfig;

pub struct VggtBench {
    pub frames: usize,
    pub height: usize,
    pub width: usize,
    pub runs: usize,
    pub warmup: usize,
    pub seed: u64,
    /// The aggregator's dtype (bf16 on a CPU with AVX512-BF16 puts the DPT heads' products in bf16 too).
    pub trunk: candle_core::DType,
}

/// Smooth synthetic frames in [0, 1], `(S, 3, H, W)`.
pub fn synthetic_frames(s: usize, h: usize, w: usize, device: &Device) -> candle_core::Result<Tensor> {
    let mut v = Vec::with_capacity(s * 3 * h * w);
    for f in 0..s {
        for c in 0..3 {
            for y in 0..h {
                for x in 0..w {
                    let t = (x as f32 * 0.037 + f as f32 * 0.9 + c as f32).sin() * (y as f32 * 0.051 - c as f32 * 0.4).cos();
                    v.push(0.5 + 0.45 * t);
                }
            }
        }
    }
    Tensor::from_vec(v, (s, 3, h, w), device)
}

/// Floating-point operations (2 per multiply-add) of one forward, from the shapes: the linear layers,
/// attention products and convolutions (norms, activations and resizes are left out).
pub fn forward_flops(cfg: &VggtConfig, s: usize, hh: usize, ww: usize) -> f64 {
    let p = cfg.patch_size;
    let (h, w) = ((hh / p) as f64, (ww / p) as f64);
    let s = s as f64;
    let c = cfg.embed_dim as f64;
    let hw = h * w;
    let block = |tokens: f64, dim: f64, seq: f64| tokens * (2.0 * dim * (3.0 * dim + dim) + 2.0 * 2.0 * dim * dim * cfg.mlp_ratio) + 4.0 * tokens * seq * dim;
    let dino_tok = 1.0 + cfg.num_register_tokens as f64 + hw;
    let mut f = s * hw * 2.0 * c * (3 * p * p) as f64;
    f += cfg.patch_embed_depth as f64 * block(s * dino_tok, c, dino_tok);
    let tok = cfg.patch_start_idx() as f64 + hw;
    f += cfg.depth as f64 * (block(s * tok, c, tok) + block(s * tok, c, s * tok));
    if cfg.enable_camera {
        let d = 2.0 * c;
        let ch = &cfg.camera_head;
        f += ch.num_iterations as f64 * (ch.trunk_depth as f64 * block(s, d, s) + s * 2.0 * (9.0 * d + d * 3.0 * d + d * d / 2.0 + d / 2.0 * 9.0));
    }
    let conv = |cin: f64, cout: f64, k: f64, px: f64| 2.0 * cin * cout * k * k * px;
    let dpt = |out: f64| {
        let o = cfg.dpt.out_channels.map(|v| v as f64);
        let fe = cfg.dpt.features as f64;
        let d = 2.0 * c;
        let px = [16.0 * hw, 4.0 * hw, hw, ((h / 2.0).ceil() * (w / 2.0).ceil())];
        let mut t = 0.0;
        for i in 0..4 {
            t += conv(d, o[i], 1.0, hw);
            t += match i {
                0 => conv(o[0], o[0], 4.0, hw),
                1 => conv(o[1], o[1], 2.0, hw),
                2 => 0.0,
                _ => conv(o[3], o[3], 3.0, px[3]),
            };
            t += conv(o[i], fe, 3.0, px[i]);
            // refinenet i: two (one for refinenet4) residual units of two 3×3 convs, then a 1×1 at the output size
            let units = if i == 3 { 1.0 } else { 2.0 };
            let out_px = if i == 0 { 4.0 * px[0] } else { px[i - 1] };
            t += units * 2.0 * conv(fe, fe, 3.0, px[i]) + conv(fe, fe, 1.0, out_px);
        }
        t += conv(fe, fe / 2.0, 3.0, 64.0 * hw);
        let full = (hh * ww) as f64;
        t + conv(fe / 2.0, 32.0, 3.0, full) + conv(32.0, out, 1.0, full)
    };
    if cfg.enable_depth {
        f += s * dpt(2.0);
    }
    if cfg.enable_point {
        f += s * dpt(4.0);
    }
    f
}

/// Build the model with random weights, run `warmup` untimed and `runs` timed forwards; one JSON line.
pub fn run(cfg: &VggtConfig, b: &VggtBench, device: &Device) -> candle_core::Result<serde_json::Value> {
    let p = cfg.patch_size;
    if b.frames == 0 || b.height % p != 0 || b.width % p != 0 || b.height == 0 || b.width == 0 {
        candle_core::bail!(
            "bench vggt: need --frames ≥ 1 and a size whose sides are positive multiples of {p} (got {} frames, {}x{})",
            b.frames,
            b.width,
            b.height
        );
    }
    let t = Instant::now();
    let model = crate::weights::random_model(cfg, b.seed, device, b.trunk)?;
    let build_ms = t.elapsed().as_secs_f64() * 1e3;
    let images = synthetic_frames(b.frames, b.height, b.width, device)?;
    let mut times = Vec::with_capacity(b.runs);
    mvsplat360_nn::prof::sync_with(device);
    for i in 0..b.warmup + b.runs.max(1) {
        if i == b.warmup {
            let _ = mvsplat360_nn::prof::take_report();
        }
        let t = Instant::now();
        let pred = model.forward(&images, &[])?;
        // Wait for the device: read one value of every output.
        for o in pred.pose_enc_list.iter().chain(pred.depth.iter().map(|d| &d.0)).chain(pred.world_points.iter().map(|d| &d.0)) {
            o.flatten_all()?.narrow(0, 0, 1)?.to_vec1::<f32>()?;
        }
        if i >= b.warmup {
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    let ms = median(times.clone());
    let profile: serde_json::Map<String, serde_json::Value> =
        mvsplat360_nn::prof::take_report().into_iter().map(|(n, ms, calls)| (n.to_string(), json!({ "ms": ms, "calls": calls }))).collect();
    let flops = forward_flops(cfg, b.frames, b.height, b.width);
    Ok(json!({
        "bench": "vggt",
        "device": format!("{device:?}"),
        "dtype": format!("{:?}", b.trunk).to_lowercase(),
        // What the trunk's big linears run on: the packed bf16 product (its path) or the trunk's dtype's gemm.
        "trunk_linears": if model.aggregator.bf16_packed() { mvsplat360_nn::bf16::path().name().to_string() } else { format!("{:?} gemm", b.trunk).to_lowercase() },
        // What the DPT heads' products run on: bf16 (the packed model's heads, `DptHead::pack_bf16`) or f32.
        "heads": if model.depth_head.as_ref().or(model.point_head.as_ref()).is_some_and(|h| h.bf16_packed()) { mvsplat360_nn::bf16::path().name().to_string() } else { "f32".to_string() },
        "frames": b.frames,
        "size": format!("{}x{}", b.width, b.height),
        "threads": rayon::current_num_threads(),
        "build_ms": build_ms,
        "forward_ms": ms,
        "runs_ms": times,
        "tflop": flops / 1e12,
        "gflop_per_s": flops / (ms / 1e3) / 1e9,
        "peak_mib": peak_rss_mib(),
        "profile": profile,
        "config": if *cfg == VggtConfig::default() { "VGGT-1B".to_string() } else { "custom".to_string() },
    }))
}
