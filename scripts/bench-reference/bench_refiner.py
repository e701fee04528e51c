#!/usr/bin/env python3
"""PyTorch reference for `mvsplat360 bench refiner`: the SVD refiner's UNet step and temporal VAE decode (CPU, or a GPU
with --device cuda --dtype bf16, for `bench scene --device cuda`'s stage times).

Models (diffusers, random weights = the default initialisers after `torch.manual_seed(--seed)`):
- `UNetSpatioTemporalConditionModel` at the SVD img2vid size as MVSplat360 uses it: in_channels 8 (4 noisy latent
  + 4 rendered-feature channels), block_out_channels (320, 640, 1280, 1280), layers_per_block 2, heads
  (5, 10, 20, 20) = 64 channels per head, cross_attention_dim 1024, addition_time_embed_dim 256 and
  projection_class_embeddings_input_dim 256 (MVSplat360's `adm_in_channels: 256`: only the cond_aug embedding),
  see shared/fixtures/svd/README.md.
- `AutoencoderKLTemporalDecoder` at the SVD size: block_out_channels (128, 256, 512, 512), layers_per_block 2,
  latent 4, scaling 0.18215.

Timed work (matching crates/refiner/src/bench.rs):
- unet_step_ms: one guided sampling step = ONE UNet call on the classifier-free-guidance batch [uncond; cond]
  (--batch 2) x --frames frames at --latent-h x --latent-w: input [x*c_in, features] (uncond: zero features),
  sigma = 700 (c_in = 1/sqrt(sigma^2+1), timestep c_noise = 0.25 ln sigma), one averaged CLIP token of 1024
  (uncond: zeros), added_time_ids = [[0.02]]. Median of --runs calls after --warmup untimed ones.
- vae_decode_ms: decoding --vae-frames latent frames (default 1) at the same latent size, one frame per decoder
  call (`num_frames=1`, MVSplat360's DL3DV `en_and_decode_n_samples_a_time: 1`), latents / 0.18215 first. Median of
  --vae-runs.
Prints one JSON line {"bench":"refiner","frames":F,"latent_h":h,"latent_w":w,"unet_step_ms":…,"vae_decode_ms":…,
"peak_mib":…,"impl":"pytorch",…}.
--autocast bf16 runs both under PyTorch's CPU bf16 autocast (f32 weights, bf16 matmuls/convolutions), the
reference for `bench refiner --dtype bf16` on the CPU; --dtype bf16 casts the weights instead.
"""

import argparse
import math
import os
import sys
import time

sys.dont_write_bytecode = True  # keep the source tree clean (no __pycache__)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import torch  # noqa: E402

from common import emit, log, median, peak_rss_mib, set_threads, time_ms  # noqa: E402

UNET_CONFIG = dict(
    sample_size=None,
    in_channels=8,
    out_channels=4,
    down_block_types=("CrossAttnDownBlockSpatioTemporal", "CrossAttnDownBlockSpatioTemporal",
                      "CrossAttnDownBlockSpatioTemporal", "DownBlockSpatioTemporal"),
    up_block_types=("UpBlockSpatioTemporal", "CrossAttnUpBlockSpatioTemporal", "CrossAttnUpBlockSpatioTemporal",
                    "CrossAttnUpBlockSpatioTemporal"),
    block_out_channels=(320, 640, 1280, 1280),
    addition_time_embed_dim=256,
    projection_class_embeddings_input_dim=256,
    layers_per_block=2,
    cross_attention_dim=1024,
    transformer_layers_per_block=1,
    num_attention_heads=(5, 10, 20, 20),
    num_frames=14,
)

VAE_CONFIG = dict(
    in_channels=3,
    out_channels=3,
    down_block_types=("DownEncoderBlock2D",) * 4,
    block_out_channels=(128, 256, 512, 512),
    layers_per_block=2,
    latent_channels=4,
    sample_size=768,
    scaling_factor=0.18215,
    force_upcast=True,
)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=14)
    ap.add_argument("--latent-h", type=int, default=64)
    ap.add_argument("--latent-w", type=int, default=112)
    ap.add_argument("--batch", type=int, default=2, help="2 = guided step [uncond; cond] (the Rust bench), 1 = cond")
    ap.add_argument("--threads", type=int, default=0, help="intra-op threads (0 = PyTorch default = all cores)")
    ap.add_argument("--runs", type=int, default=1, help="timed UNet calls (a full-size call takes minutes)")
    ap.add_argument("--warmup", type=int, default=0, help="untimed UNet calls first (the Rust bench does none)")
    ap.add_argument("--vae-frames", type=int, default=1, help="latent frames decoded (one per decoder call)")
    ap.add_argument("--vae-runs", type=int, default=1)
    ap.add_argument("--skip-vae", action="store_true")
    ap.add_argument("--skip-unet", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (inputs are drawn on the CPU, then moved)")
    ap.add_argument("--dtype", default="f32", choices=["f32", "f16", "bf16"], help="weights and inputs (GPU: bf16)")
    ap.add_argument("--autocast", default="off", choices=["off", "bf16"],
                    help="bf16: f32 weights and inputs, the calls under torch.autocast(device, bfloat16) (PyTorch's "
                         "mixed precision: matmuls and convolutions in bf16 through oneDNN on the CPU)")
    args = ap.parse_args()
    dev = torch.device(args.device)
    dtype = {"f32": torch.float32, "f16": torch.float16, "bf16": torch.bfloat16}[args.dtype]
    set_threads(args.threads)
    if args.autocast != "off" and dtype != torch.float32:
        sys.exit("--autocast bf16 takes f32 weights: leave --dtype at f32")
    import contextlib
    autocast = (lambda: torch.autocast(dev.type, dtype=torch.bfloat16)) if args.autocast == "bf16" else contextlib.nullcontext
    from diffusers import AutoencoderKLTemporalDecoder, UNetSpatioTemporalConditionModel

    F, h, w, B = args.frames, args.latent_h, args.latent_w, args.batch
    if h % 8 or w % 8:
        sys.exit("--latent-h/--latent-w must be multiples of 8 (three 2x downsamplings)")
    rec = {"bench": "refiner", "frames": F, "latent_h": h, "latent_w": w, "batch": B}
    g = torch.Generator().manual_seed(args.seed + 1)

    if not args.skip_unet:
        torch.manual_seed(args.seed)
        t0 = time.perf_counter()
        unet = UNetSpatioTemporalConditionModel(**UNET_CONFIG).eval().to(dev, dtype)
        init_ms = (time.perf_counter() - t0) * 1e3
        n_params = sum(p.numel() for p in unet.parameters())
        sigma = 700.0
        c_in = 1.0 / math.sqrt(sigma * sigma + 1.0)
        c_noise = 0.25 * math.log(sigma)
        x = torch.randn(1, F, 4, h, w, generator=g) * math.sqrt(1.0 + sigma * sigma)
        feats = torch.randn(1, F, 4, h, w, generator=g)
        clip = torch.randn(1, 1, 1024, generator=g)
        if B == 2:  # [uncond; cond]: zero features and zero CLIP token for the unconditional half
            sample = torch.cat([torch.cat([x * c_in, torch.zeros_like(feats)], 2), torch.cat([x * c_in, feats], 2)])
            ctx = torch.cat([torch.zeros_like(clip), clip])
        elif B == 1:
            sample, ctx = torch.cat([x * c_in, feats], 2), clip
        else:
            sys.exit("--batch must be 1 or 2")
        timestep = torch.full((B,), c_noise)
        added_time_ids = torch.full((B, 1), 0.02)
        sample, ctx, timestep, added_time_ids = (t.to(dev, dtype) for t in (sample, ctx, timestep, added_time_ids))
        log(f"unet: {n_params} parameters ({init_ms:.0f} ms to build), input {tuple(sample.shape)}, "
            f"{torch.get_num_threads()} threads")
        out = {}

        def step():
            with torch.no_grad(), autocast():
                out["v"] = unet(sample, timestep, encoder_hidden_states=ctx, added_time_ids=added_time_ids,
                                return_dict=False)[0]
            out["v"].sum().item()

        times = time_ms(step, args.runs, args.warmup)
        rec.update({"unet_step_ms": round(median(times), 3), "unet_step_runs_ms": [round(t, 3) for t in times],
                    "unet_params": n_params, "unet_init_ms": round(init_ms, 1),
                    "unet_output_finite": bool(torch.isfinite(out["v"]).all())})
        del unet, out

    if not args.skip_vae:
        torch.manual_seed(args.seed + 2)
        vae = AutoencoderKLTemporalDecoder(**VAE_CONFIG).eval().to(dev, dtype)
        n_params = sum(p.numel() for p in vae.decoder.parameters())
        z = torch.randn(args.vae_frames, 4, h, w, generator=g).to(dev, dtype)
        log(f"vae decoder: {n_params} parameters, {args.vae_frames} frame(s) {h}x{w} latents -> {8 * h}x{8 * w}")
        res = {}

        def decode():
            with torch.no_grad(), autocast():
                frames = [vae.decode(z[i:i + 1] / VAE_CONFIG["scaling_factor"], num_frames=1).sample
                          for i in range(z.shape[0])]
            res["img"] = torch.cat(frames).float()
            res["img"].sum().item()

        vt = time_ms(decode, args.vae_runs, warmup=0)
        rec.update({"vae_decode_ms": round(median(vt), 3), "vae_frames": args.vae_frames,
                    "vae_decoder_params": n_params, "vae_output_shape": list(res["img"].shape),
                    "vae_output_finite": bool(torch.isfinite(res["img"]).all())})

    rec.update({"peak_mib": round(peak_rss_mib(), 1), "threads": torch.get_num_threads(),
                "torch": torch.__version__, "device": str(dev), "dtype": args.dtype, "autocast": args.autocast})
    if dev.type == "cuda":
        rec["gpu_peak_mib"] = round(torch.cuda.max_memory_allocated(dev) / 2**20, 1)
        rec["gpu_name"] = torch.cuda.get_device_name(dev)
    import diffusers
    rec["diffusers"] = diffusers.__version__
    emit(rec)


if __name__ == "__main__":
    main()
