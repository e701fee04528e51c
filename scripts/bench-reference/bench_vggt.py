#!/usr/bin/env python3
"""PyTorch reference for `mvsplat360 bench vggt`: the OFFICIAL VGGT (facebookresearch/vggt at 44b3afb) forward.

The model code is imported at run time from a checkout of the official repository (`--repo`, default $VGGT_REF or
/work/ref/vggt); nothing of it is copied here. Model = `VGGT(enable_track=False)`: the aggregator and the camera,
depth and point heads (the same scope as the Rust bench), random weights (`torch.manual_seed(--seed)` then the
official initialisers), float32 on the CPU, `torch.no_grad()`, eval mode. Input = the same synthetic frames as the
Rust bench (`crates/vggt/src/bench.rs`, `synthetic_frames`).

Prints one JSON line:
  {"bench":"vggt","frames":S,"size":"WxH","forward_ms":…,"peak_mib":…,"impl":"pytorch",…}
forward_ms = median of --runs forwards after --warmup untimed ones; peak_mib = ru_maxrss (model included).
"""

import argparse
import os
import sys

sys.dont_write_bytecode = True
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import torch  # noqa: E402

from common import emit, log, median, peak_rss_mib, set_threads, time_ms  # noqa: E402


def synthetic_frames(s, h, w):
    f = torch.arange(s, dtype=torch.float32).view(s, 1, 1, 1)
    c = torch.arange(3, dtype=torch.float32).view(1, 3, 1, 1)
    y = torch.arange(h, dtype=torch.float32).view(1, 1, h, 1)
    x = torch.arange(w, dtype=torch.float32).view(1, 1, 1, w)
    t = torch.sin(x * 0.037 + f * 0.9 + c) * torch.cos(y * 0.051 - c * 0.4)
    return 0.5 + 0.45 * t


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repo", default=os.environ.get("VGGT_REF", "/work/ref/vggt"))
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--size", default="518x294", help="WIDTHxHEIGHT")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    set_threads(a.threads)
    sys.path.insert(0, a.repo)
    from vggt.models.vggt import VGGT

    w, h = (int(v) for v in a.size.split("x"))
    torch.manual_seed(a.seed)
    model = VGGT(enable_track=False).eval()
    images = synthetic_frames(a.frames, h, w)
    log(f"VGGT {sum(p.numel() for p in model.parameters())} parameters; {a.frames} frames {w}x{h}")

    def fwd():
        with torch.no_grad():
            model(images)

    times = time_ms(fwd, a.runs, a.warmup)
    emit({
        "bench": "vggt",
        "frames": a.frames,
        "size": a.size,
        "threads": torch.get_num_threads(),
        "forward_ms": median(times),
        "runs_ms": times,
        "peak_mib": peak_rss_mib(),
        "torch": torch.__version__,
    })


if __name__ == "__main__":
    main()
