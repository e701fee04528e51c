#!/usr/bin/env python3
"""PyTorch reference for `mvsplat360 bench encoder`: the OFFICIAL MVSplat360 `EncoderCostVolume` (DL3DV config).

The encoder code is imported at run time from a checkout of donydchen/mvsplat360 (`--repo`); nothing of it is copied
here. Configuration = hydra `main` + `+experiment=dl3dv_mvsplat360 mode=test dataset/view_sampler=evaluation
checkpointing.pretrained_model=null dataset.view_sampler.num_context_views=<views>` (as the encoder fixtures in
shared/fixtures/encoder were made), random weights (`torch.manual_seed(--seed)` then the official initialisers), no
pretrained backbone. Input = the same synthetic context as the Rust bench (`crates/encoder/src/bench.rs`,
`synthetic_context`): smooth images, cameras on an arc looking at the origin, normalised K, near 1, far 100.

Prints one JSON line:
  {"bench":"encoder","views":V,"height":H,"width":W,"forward_ms":…,"peak_mib":…,"impl":"pytorch",…}
forward_ms = median of --runs `torch.no_grad()` forwards after --warmup untimed ones; peak_mib = ru_maxrss.
"""

import argparse
import importlib.abc
import importlib.machinery
import math
import os
import sys
import types
import warnings

sys.dont_write_bytecode = True  # keep the source tree clean (no __pycache__)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import torch  # noqa: E402

from common import emit, log, median, peak_rss_mib, set_threads, time_ms  # noqa: E402

# Third-party packages the encoder package imports only for visualisation / data / logging code. They are replaced
# by permissive placeholder modules (any attribute, any submodule), as the fixture generator did.
PLACEHOLDER_PACKAGES = ("wandb", "matplotlib", "colorspacious", "torchvision", "pytorch_lightning", "skvideo", "cv2")


class _AnyMeta(type):
    def __getattr__(cls, name):
        if name.startswith("__") and name.endswith("__"):
            raise AttributeError(name)
        return _Any


class _Any(metaclass=_AnyMeta):
    """Stands for any class, function or value of a placeholder package (callable, subclassable)."""

    def __init__(self, *args, **kwargs):
        pass

    def __call__(self, *args, **kwargs):
        return _Any()

    def __getattr__(self, name):
        if name.startswith("__") and name.endswith("__"):
            raise AttributeError(name)
        return _Any()


class _PlaceholderModule(types.ModuleType):
    def __getattr__(self, name):
        if name.startswith("__") and name.endswith("__"):
            raise AttributeError(name)
        return _Any


class _PlaceholderFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    def find_spec(self, fullname, path=None, target=None):
        if fullname.split(".")[0] in PLACEHOLDER_PACKAGES:
            return importlib.machinery.ModuleSpec(fullname, self, is_package=True)
        return None

    def create_module(self, spec):
        m = _PlaceholderModule(spec.name)
        m.__path__ = []
        return m

    def exec_module(self, module):
        pass


def install_placeholders():
    if any(isinstance(f, _PlaceholderFinder) for f in sys.meta_path):
        return
    for name in list(sys.modules):
        if name.split(".")[0] in PLACEHOLDER_PACKAGES:
            del sys.modules[name]
    sys.meta_path.insert(0, _PlaceholderFinder())


def synthetic_context(b: int, v: int, h: int, w: int):
    """Exactly `synthetic_context` of crates/encoder/src/bench.rs (float32)."""
    ys = torch.arange(h, dtype=torch.float32).view(h, 1)
    xs = torch.arange(w, dtype=torch.float32).view(1, w)
    img = torch.empty(b, v, 3, h, w)
    for bi in range(b):
        for vi in range(v):
            for c in range(3):
                t = torch.sin(xs * 0.05 + ys * 0.03 + float(vi + bi) * 0.7 + float(c))
                img[bi, vi, c] = 0.5 + 0.4 * t
    ext = torch.zeros(b, v, 4, 4)
    for bi in range(b):
        for vi in range(v):
            ang = -1.0 + 2.0 * vi / (max(v, 2) - 1)
            c = torch.tensor([2.0 * math.sin(ang), 0.05 * vi, -2.0 * math.cos(ang)])
            z = -c / c.norm()  # look at the origin (OpenCV: +z forward, +y down)
            down = torch.tensor([0.0, 1.0, 0.0])
            x = torch.linalg.cross(down, z)
            x = x / x.norm()
            y = torch.linalg.cross(z, x)
            ext[bi, vi, :3, 0], ext[bi, vi, :3, 1], ext[bi, vi, :3, 2], ext[bi, vi, :3, 3] = x, y, z, c
            ext[bi, vi, 3, 3] = 1.0
    k = torch.tensor([[0.75, 0.0, 0.5], [0.0, 1.3, 0.5], [0.0, 0.0, 1.0]])
    return {
        "image": img,
        "extrinsics": ext,  # camera-to-world
        "intrinsics": k.expand(b, v, 3, 3).contiguous(),  # normalised
        "near": torch.ones(b, v),
        "far": torch.full((b, v), 100.0),
    }


def build_encoder(repo: str, views: int, typecheck: bool):
    repo = os.path.abspath(repo)
    if not os.path.isfile(os.path.join(repo, "src", "model", "encoder", "encoder_costvolume.py")):
        sys.exit(f"--repo {repo}: not a donydchen/mvsplat360 checkout (src/model/encoder/encoder_costvolume.py missing)")
    install_placeholders()
    if repo not in sys.path:
        sys.path.insert(0, repo)

    from hydra import compose, initialize_config_dir

    warnings.filterwarnings("ignore", message=".*Defaults list is missing")

    with initialize_config_dir(config_dir=os.path.join(repo, "config"), version_base=None):
        cfg_dict = compose(
            config_name="main",
            overrides=[
                "+experiment=dl3dv_mvsplat360",
                "mode=test",
                "dataset/view_sampler=evaluation",
                "checkpointing.pretrained_model=null",
                f"dataset.view_sampler.num_context_views={views}",
            ],
        )

    if typecheck:  # as src/main.py: beartype + jaxtyping runtime checks on every annotated call
        from jaxtyping import install_import_hook

        with install_import_hook(("src",), ("beartype", "beartype")):
            from src.global_cfg import set_cfg
            from src.model.encoder import EncoderCostVolume, EncoderCostVolumeCfg
    else:
        from src.global_cfg import set_cfg
        from src.model.encoder import EncoderCostVolume, EncoderCostVolumeCfg

    # src.config.load_typed_config, inlined: importing src.config would pull in the refiner / Lightning wrapper
    # (sgm, moviepy, ...), which the encoder does not need.
    from dacite import Config, from_dict
    from omegaconf import OmegaConf
    from pathlib import Path

    set_cfg(cfg_dict)  # the encoder reads dataset.view_sampler.num_context_views and checkpointing from it
    enc_cfg = from_dict(EncoderCostVolumeCfg, OmegaConf.to_container(cfg_dict.model.encoder),
                        config=Config(type_hooks={Path: Path}))
    return EncoderCostVolume(enc_cfg).eval(), enc_cfg


def check_fixture(encoder, fixture_dir: str) -> float:
    """Load shared/fixtures/encoder (state dict + inputs) into `encoder`, run the forward and return the worst
    normalised error max|d| / max(1, max|ref|) (the fixture README's measure) over the Gaussian outputs."""
    from safetensors.torch import load_file

    sd = load_file(os.path.join(fixture_dir, "state_dict.safetensors"))
    sd = {k[len("encoder."):]: v for k, v in sd.items()}
    missing, unexpected = encoder.load_state_dict(sd, strict=False)
    if missing or unexpected:
        sys.exit(f"fixture state dict: missing {missing}, unexpected {unexpected}")
    inp = load_file(os.path.join(fixture_dir, "inputs.safetensors"))
    ref = load_file(os.path.join(fixture_dir, "outputs.safetensors"))
    context = {k[len("context."):]: v for k, v in inp.items()}
    with torch.no_grad():
        g = encoder(context, global_step=0, deterministic=False)
    worst = 0.0
    for name in ("opacities", "harmonics", "feature_harmonics", "means", "covariances"):
        r = ref[f"gaussians.{name}"]
        e = (getattr(g, name) - r).abs().max().item() / max(1.0, r.abs().max().item())
        log(f"fixture check: gaussians.{name} normalised max-abs error {e:.3g}")
        worst = max(worst, e)
    return worst


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repo", required=True, help="checkout of donydchen/mvsplat360 (contains src/ and config/)")
    ap.add_argument("--views", type=int, default=5)
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--width", type=int, default=448)
    ap.add_argument("--threads", type=int, default=0, help="intra-op threads (0 = PyTorch default = all cores)")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--typecheck", action="store_true",
                    help="import the encoder under jaxtyping+beartype as src/main.py does (slower; off by default)")
    ap.add_argument("--check-fixture", metavar="DIR",
                    help="first load shared/fixtures/encoder (5 views, 32x64) into the built encoder and compare its "
                         "outputs (needs --views 5), then re-draw random weights and benchmark as usual")
    args = ap.parse_args()
    if args.views < 3:
        sys.exit("--views must be >= 3: the official nearest-view selection asserts at least 3 context views")
    if args.height % 16 or args.width % 16:
        sys.exit("--height and --width must be multiples of 16 (the encoder's UNets and 2x2 windows need it)")
    set_threads(args.threads)

    if args.check_fixture:
        if args.views != 5:
            sys.exit("--check-fixture needs --views 5 (the fixture's context size)")
        e = check_fixture(build_encoder(args.repo, 5, args.typecheck)[0], args.check_fixture)
        if e > 2e-3:
            sys.exit(f"fixture check FAILED: normalised max-abs error {e:.3g} > 2e-3")
        log(f"fixture check passed (worst normalised error {e:.3g} <= 2e-3)")
    torch.manual_seed(args.seed)  # random weights: the official initialisers under this seed
    encoder, _ = build_encoder(args.repo, args.views, args.typecheck)
    n_params = sum(p.numel() for p in encoder.parameters())
    context = synthetic_context(1, args.views, args.height, args.width)

    def forward():
        with torch.no_grad():
            g = encoder(context, global_step=0, deterministic=False)
            g.means.sum().item()

    log(f"encoder: {n_params} parameters, {args.views} views {args.height}x{args.width}, "
        f"{torch.get_num_threads()} threads")
    times = time_ms(forward, args.runs, args.warmup)
    emit({"bench": "encoder", "views": args.views, "height": args.height, "width": args.width,
          "forward_ms": round(median(times), 3), "peak_mib": round(peak_rss_mib(), 1),
          "runs_ms": [round(t, 3) for t in times], "threads": torch.get_num_threads(),
          "params": n_params, "typecheck": args.typecheck, "torch": torch.__version__})


if __name__ == "__main__":
    main()
