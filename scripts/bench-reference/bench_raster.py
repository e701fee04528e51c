#!/usr/bin/env python3
"""PyTorch reference for `mvsplat360 bench raster`: a pure-PyTorch (CPU, vectorised) 3DGS rasterizer.

Semantics = shared/fixtures/rasterizer/README.md (the latentSplat fork of graphdeco's rasterizer that MVSplat360
uses): world->view, 3D covariance from scale + (w,x,y,z) quaternion (not normalised), EWA Jacobian with the
1.3*tan(fov) clamp, +0.3 low-pass, 3-sigma radius, 16x16 tiles (rect from truncated divisions), per-tile sort by
view depth, front-to-back compositing alpha = min(0.99, o*exp(power)), skip alpha < 1/255 or power > 0, stop when
T*(1-alpha) < 1e-4; RGB from SH degrees 0..3 (e3nn axis order, +0.5, clamped >= 0) plus background, C feature
channels (per-Gaussian values, no background, the fork's stop-gradient: feature weights are detached), accumulated
alpha and expected depth.

Vectorisation (gsplat pure-torch style): all tile/Gaussian pairs are listed and sorted by (tile, depth rank); each
tile's list is padded into a [tiles, L] index matrix; compositing walks the lists in chunks of --chunk Gaussians for
all still-active tiles at once ([tiles, 256 pixels, chunk] tensors), transmittance by cumprod carried across chunks;
tiles whose pixels have all stopped (or whose lists ended) drop out (the early stop). Backward = autograd; each
chunk runs under torch.utils.checkpoint (recomputed in backward) so memory stays ~one chunk instead of
pairs x 256 pixels. Gradients are the true derivative of the forward except the feature stop-gradient (the fork's
other backward quirks - alpha clamp, Jacobian clamp, det^2+1e-7, SH coefficient 14 - are not emulated; they do not
change the amount of work).

Workload (specified in README.md, "Synthetic raster scene"; `mvsplat360 bench raster` must generate the same): N
pixel-aligned, depth-layered Gaussians from source views of W x H pixels (default 5 views -> N = 5*W*H = 573,440 at
448x256) rendered into one W x H view with C features. Prints one JSON line:
  {"bench":"raster","gaussians":N,"width":W,"height":H,"features":C,"forward_ms":…,"forward_backward_ms":…,
   "impl":"pytorch",…}
(medians of --runs after one warm-up each).
"""

import argparse
import math
import os
import sys

sys.dont_write_bytecode = True  # keep the source tree clean (no __pycache__)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import torch  # noqa: E402
import torch.utils.checkpoint  # noqa: E402

from common import emit, log, median, peak_rss_mib, set_threads, time_ms  # noqa: E402

TILE = 16
C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435)


# ----------------------------------------------------------------------------------------------------------------
# Rasterizer
# ----------------------------------------------------------------------------------------------------------------

def quat_to_rotmat(q):
    """(w,x,y,z) -> 3x3, not normalised (graphdeco computeCov3D without the normalisation)."""
    r, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - r * z), 2 * (x * z + r * y),
        2 * (x * y + r * z), 1 - 2 * (x * x + z * z), 2 * (y * z - r * x),
        2 * (x * z - r * y), 2 * (y * z + r * x), 1 - 2 * (x * x + y * y),
    ], -1).view(*q.shape[:-1], 3, 3)


def sh_to_color(sh, dirs):
    """Degrees 0..3 of (N,>=16,3) SH with the fork's e3nn axis order; colour = max(sum + 0.5, 0)."""
    x, y, z = (dirs[:, i:i + 1] for i in range(3))
    xx, yy, zz = x * x, y * y, z * z
    s = sh
    res = C0 * s[:, 0]
    res = res - C1 * x * s[:, 1] + C1 * y * s[:, 2] - C1 * z * s[:, 3]
    res = (res + C2[0] * z * x * s[:, 4] + C2[1] * x * y * s[:, 5] + C2[2] * (2 * yy - zz - xx) * s[:, 6]
           + C2[3] * z * y * s[:, 7] + C2[4] * (zz - xx) * s[:, 8])
    res = (res + C3[0] * x * (3 * zz - xx) * s[:, 9] + C3[1] * z * x * y * s[:, 10]
           + C3[2] * x * (4 * yy - zz - xx) * s[:, 11] + C3[3] * y * (2 * yy - 3 * zz - 3 * xx) * s[:, 12]
           + C3[4] * z * (4 * yy - zz - xx) * s[:, 13] + C3[5] * z * (zz - xx) * s[:, 14]
           + C3[6] * z * (zz - 3 * xx) * s[:, 15])
    return torch.clamp_min(res + 0.5, 0.0)


def mm3(a, b):
    """Batched (n,r,3) x (n,3,c) product as explicit elementwise sums in k order: deterministic rounding (a BLAS bmm
    may round differently run to run, which flips borderline radii / alpha tests) and the kernel's summation order."""
    return a[:, :, 0:1] * b[:, 0:1, :] + a[:, :, 1:2] * b[:, 1:2, :] + a[:, :, 2:3] * b[:, 2:3, :]


def project(means, scales, quats, viewmat, fx, fy, cx, cy, width, height):
    """Per-Gaussian screen-space quantities. Returns means2d (N,2), conic (N,3), depth z (N,), radii (int, N),
    rect (N,4 int: x0,y0,x1,y1 in tiles) and the visibility mask."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    # p_view summed in the kernel's order (transformPoint4x3): matches the fixture's depths bit for bit
    p = torch.stack([R[i, 0] * means[:, 0] + R[i, 1] * means[:, 1] + R[i, 2] * means[:, 2] + t[i] for i in range(3)], -1)
    z = p[:, 2]
    valid = z > 0.2
    zs = torch.where(valid, z, torch.ones_like(z))  # keeps culled Gaussians finite (no NaN in autograd)
    rot = quat_to_rotmat(quats)
    m = rot * scales[:, None, :]  # R diag(s)
    cov3 = mm3(m, m.transpose(1, 2))  # R diag(s)^2 R^T (world)
    f32 = lambda v: torch.tensor(v, dtype=torch.float32)  # noqa: E731
    tanx, tany = f32(width) / (2 * f32(fx)), f32(height) / (2 * f32(fy))  # float32 as the kernel
    fxk, fyk = f32(width) / (2 * tanx), f32(height) / (2 * tany)  # the kernel's recomputed focal lengths
    limx, limy = 1.3 * tanx, 1.3 * tany
    tx = torch.clamp(p[:, 0] / zs, -limx, limx) * zs
    ty = torch.clamp(p[:, 1] / zs, -limy, limy) * zs
    zero = torch.zeros_like(zs)
    J = torch.stack([fxk / zs, zero, -(fxk * tx) / (zs * zs), zero, fyk / zs, -(fyk * ty) / (zs * zs)], -1).view(-1, 2, 3)
    T = mm3(J, R.expand(J.shape[0], 3, 3))
    cov2 = mm3(mm3(T, cov3), T.transpose(1, 2))
    a = cov2[:, 0, 0] + 0.3
    b = cov2[:, 0, 1]
    c = cov2[:, 1, 1] + 0.3
    det = a * c - b * b
    valid = valid & (det != 0)
    dets = torch.where(valid, det, torch.ones_like(det))
    det_inv = 1.0 / dets  # the kernel multiplies by the reciprocal
    conic = torch.stack([c * det_inv, -b * det_inv, a * det_inv], -1)
    # Screen position as the kernel: p_hom = full_proj @ [p, 1] in float32 (full_proj = P @ viewmat),
    # p_proj = p_hom * (1 / (p_hom.w + 1e-7)), then ndc2Pix ((v + 1) * size - 1) * 0.5 in double, cast to float32.
    P = torch.zeros(4, 4)
    P[0, 0], P[1, 1] = 2.0 * fx / width, 2.0 * fy / height
    P[0, 2], P[1, 2], P[3, 2] = 2.0 * cx / width - 1.0, 2.0 * cy / height - 1.0, 1.0
    full = P @ viewmat
    hom = [full[i, 0] * means[:, 0] + full[i, 1] * means[:, 1] + full[i, 2] * means[:, 2] + full[i, 3]
           for i in (0, 1, 3)]
    p_w = 1.0 / (torch.where(valid, hom[2], torch.ones_like(hom[2])) + 1e-7)  # hom.w = z; culled rows kept finite
    means2d = torch.stack([(((hom[0] * p_w).double() + 1.0) * width - 1.0) * 0.5,
                           (((hom[1] * p_w).double() + 1.0) * height - 1.0) * 0.5], -1).float()
    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt(torch.clamp_min(mid * mid - det, 0.1))
        radii = torch.ceil(3.0 * torch.sqrt(lam))
        gx, gy = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
        mx, my = means2d[:, 0], means2d[:, 1]
        x0 = torch.clamp(torch.trunc((mx - radii) / TILE), 0, gx)
        y0 = torch.clamp(torch.trunc((my - radii) / TILE), 0, gy)
        x1 = torch.clamp(torch.trunc((mx + radii + TILE - 1) / TILE), 0, gx)
        y1 = torch.clamp(torch.trunc((my + radii + TILE - 1) / TILE), 0, gy)
        rect = torch.stack([x0, y0, x1, y1], -1).long()
        valid = valid & ((x1 - x0) * (y1 - y0) > 0)
        radii = torch.where(valid, radii, torch.zeros_like(radii)).int()
    return means2d, conic, z, radii, rect, valid


def bin_and_sort(rect, depth, gx):
    """Tile/Gaussian pairs of the M visible Gaussians sorted by (tile, depth, index). Returns the Gaussian (0..M-1)
    of each pair and the tile of each pair."""
    x0, y0, x1, y1 = rect.unbind(-1)
    nx, ny = x1 - x0, y1 - y0
    cnt = nx * ny
    m = rect.shape[0]
    gid = torch.repeat_interleave(torch.arange(m), cnt)
    start = torch.cumsum(cnt, 0) - cnt
    local = torch.arange(gid.numel()) - start[gid]
    tile = (y0[gid] + local // nx[gid]) * gx + (x0[gid] + local % nx[gid])
    rank = torch.empty(m, dtype=torch.long)
    rank[torch.sort(depth, stable=True).indices] = torch.arange(m)
    order = torch.sort(tile * m + rank[gid]).indices
    return gid[order], tile[order]


def _composite_chunk(T_in, done_in, px, py, gidx, means2d, conic, opac, color, feat, depth):
    """Blend one chunk of K list entries into the active tiles. T_in/done_in: [A,P]; px,py: [A,P]; gidx: [A,K] into
    the padded per-Gaussian arrays (last row = padding). Returns T_out, done_out, rgb [A,P,3], feat [A,P,C],
    depth [A,P]."""
    m2 = means2d[gidx]  # [A,K,2]
    co = conic[gidx]  # [A,K,3]
    dx = m2[:, None, :, 0] - px[:, :, None]  # [A,P,K]
    dy = m2[:, None, :, 1] - py[:, :, None]
    power = -0.5 * (co[:, None, :, 0] * dx * dx + co[:, None, :, 2] * dy * dy) - co[:, None, :, 1] * dx * dy
    alpha = torch.clamp_max(opac[gidx][:, None, :] * torch.exp(power), 0.99)
    alpha = torch.where((power > 0) | (alpha < 1.0 / 255.0), torch.zeros_like(alpha), alpha)
    one_minus = 1.0 - alpha
    cp = torch.cumprod(one_minus, dim=2)
    T_after = T_in[:, :, None] * cp
    T_before = T_in[:, :, None] * torch.cat([torch.ones_like(cp[:, :, :1]), cp[:, :, :-1]], dim=2)
    live = (alpha > 0) & ~done_in[:, :, None]
    stop = live & (T_after < 1e-4)
    blend = live & ~stop
    w = torch.where(blend, alpha * T_before, torch.zeros_like(alpha))
    T_out = T_in * torch.prod(torch.where(blend, one_minus, torch.ones_like(one_minus)), dim=2)
    done_out = done_in | stop.any(dim=2)
    rgb = torch.einsum("apk,akc->apc", w, color[gidx])
    fe = torch.einsum("apk,akc->apc", w.detach(), feat[gidx])  # the fork's feature stop-gradient
    dep = torch.einsum("apk,ak->ap", w, depth[gidx])
    return T_out, done_out, rgb, fe, dep


def rasterize(means, scales, quats, opacities, sh, features, viewmat, intr, width, height, background,
              chunk=32, checkpoint=True):
    """Returns dict with rgb (H,W,3), feat (H,W,C), alpha (H,W), depth (H,W), radii (N,), means2d, conic, colors."""
    fx, fy, cx, cy = intr
    C = features.shape[1]
    means2d, conic, z, radii, rect, valid = project(means, scales, quats, viewmat, fx, fy, cx, cy, width, height)
    campos = -viewmat[:3, :3].T @ viewmat[:3, 3]
    vis = torch.nonzero(valid).squeeze(1)
    mv = means[vis]
    dirs = mv - campos
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    color = sh_to_color(sh[vis], dirs)
    gx, gy = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    n_tiles = gx * gy
    M = vis.numel()
    pad1 = lambda x: torch.cat([x, torch.zeros_like(x[:1])], 0)  # noqa: E731  (row M = padding entry)
    g_m2, g_co, g_op = pad1(means2d[vis]), pad1(conic[vis]), pad1(opacities[vis])
    g_col, g_feat, g_dep = pad1(color), pad1(features[vis]), pad1(z[vis])

    with torch.no_grad():
        pair_g, pair_t = bin_and_sort(rect[vis], z[vis], gx)
        counts = torch.bincount(pair_t, minlength=n_tiles)
        L = int(counts.max()) if pair_g.numel() else 0
        starts = torch.cumsum(counts, 0) - counts
        lists = torch.full((n_tiles, max(L, 1)), M, dtype=torch.long)
        pos = torch.arange(pair_g.numel()) - starts[pair_t]
        lists[pair_t, pos] = pair_g
        ty, tx = torch.meshgrid(torch.arange(gy), torch.arange(gx), indexing="ij")
        ly, lx = torch.meshgrid(torch.arange(TILE), torch.arange(TILE), indexing="ij")
        PX = (tx.reshape(-1, 1) * TILE + lx.reshape(1, -1)).float()  # [tiles, 256]
        PY = (ty.reshape(-1, 1) * TILE + ly.reshape(1, -1)).float()
        outside = (PX >= width) | (PY >= height)

    P = TILE * TILE
    T = torch.ones(n_tiles, P)
    done = outside.clone()
    rgb = torch.zeros(n_tiles, P, 3)
    fe = torch.zeros(n_tiles, P, C)
    dep = torch.zeros(n_tiles, P)
    active = torch.nonzero((counts > 0) & ~done.all(1)).squeeze(1)
    need_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means, scales, quats, opacities, sh, features))
    for k0 in range(0, L, chunk):
        if active.numel() == 0:
            break
        gidx = lists[active, k0:k0 + chunk]
        args = (T[active], done[active], PX[active], PY[active], gidx, g_m2, g_co, g_op, g_col, g_feat, g_dep)
        if need_grad and checkpoint:
            To, do, r, f, d = torch.utils.checkpoint.checkpoint(_composite_chunk, *args, use_reentrant=False)
        else:
            To, do, r, f, d = _composite_chunk(*args)
        T = T.index_copy(0, active, To)
        done = done.index_copy(0, active, do)
        rgb = rgb.index_add(0, active, r)
        fe = fe.index_add(0, active, f)
        dep = dep.index_add(0, active, d)
        keep = (~do.all(1)) & (counts[active] > k0 + chunk)
        active = active[keep]

    rgb = rgb + T[:, :, None] * background
    def to_img(x):  # [tiles, 256, ...] -> [H, W, ...]
        x = x.reshape(gy, gx, TILE, TILE, *x.shape[2:]).transpose(1, 2)
        return x.reshape(gy * TILE, gx * TILE, *x.shape[4:])[:height, :width]
    colors = torch.zeros(means.shape[0], 3).index_copy(0, vis, color.detach())
    return {"rgb": to_img(rgb), "feat": to_img(fe), "alpha": to_img(1.0 - T), "depth": to_img(dep),
            "final_T": to_img(T), "radii": radii, "means2d": means2d, "conic": conic, "colors": colors,
            "pairs": pair_g.numel(), "visible": M, "max_list": L}


# ----------------------------------------------------------------------------------------------------------------
# Synthetic scene (specified in README.md; the Rust bench generates the same scene)
# ----------------------------------------------------------------------------------------------------------------

MASK32 = 0xFFFFFFFF


def lowbias32(x):
    """Chris Wellons' lowbias32 integer hash on uint32 values held in int64 tensors (wrapping arithmetic)."""
    x = x & MASK32
    x = x ^ (x >> 16)
    x = (x * 0x7FEB352D) & MASK32
    x = x ^ (x >> 15)
    x = (x * 0x846CA68B) & MASK32
    x = x ^ (x >> 16)
    return x


def uniform(stream: int, idx):
    """u(stream, i) = (lowbias32(i ^ lowbias32(stream)) >> 8) * 2^-24, in [0,1), float32."""
    s = int(lowbias32(torch.tensor(stream, dtype=torch.long)))
    return (lowbias32((idx & MASK32) ^ s) >> 8).float() * (1.0 / 16777216.0)


def look_at_origin(theta: float, height: float):
    """c2w (4x4) of a camera at (2 sin t, height, -2 cos t) looking at the origin, OpenCV axes (the encoder bench's
    construction: z = -c/|c|, x = normalise((0,1,0) x z), y = z x x)."""
    c = torch.tensor([2.0 * math.sin(theta), height, -2.0 * math.cos(theta)])
    zc = -c / c.norm()
    xc = torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0]), zc)
    xc = xc / xc.norm()
    yc = torch.linalg.cross(zc, xc)
    c2w = torch.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = xc, yc, zc, c
    return c2w


LAYER_DEPTHS = (1.5, 2.5, 4.0, 8.0)


def synthetic_scene(n: int, width: int, height: int, n_features: int):
    """N pixel-aligned, depth-layered Gaussians from source views of width x height (see README.md)."""
    fx, fy, cx, cy = 0.75 * width, 1.3 * height, 0.5 * width, 0.5 * height
    g = torch.arange(n, dtype=torch.long)
    hw = width * height
    s, p = g // hw, g % hw
    px, py = p % width, p // width
    n_src = (n + hw - 1) // hw
    c2ws = torch.stack([look_at_origin(-0.5 + 0.25 * (v % 5), 0.05 * (v // 5)) for v in range(n_src)])
    u = (px.float() + uniform(0, g) - cx) / fx  # jittered position inside the pixel, camera ray (z = 1)
    v = (py.float() + uniform(1, g) - cy) / fy
    ray = torch.stack([u, v, torch.ones_like(u)], -1)
    ray = ray / ray.norm(dim=1, keepdim=True)
    ray_w = torch.einsum("nij,nj->ni", c2ws[s, :3, :3], ray)
    block = s * 1_000_000 + (py // 32) * 1000 + px // 32  # 32x32-pixel blocks share a depth layer
    layer = torch.clamp((5.0 * uniform(2, block)).long(), max=3)  # layer 3 (background) in 40% of blocks
    d = torch.tensor(LAYER_DEPTHS)[layer] * (0.95 + 0.1 * uniform(3, g))
    means = c2ws[s, :3, 3] + d[:, None] * ray_w
    foot = d / fx  # world size of one pixel at that distance
    scales = foot[:, None] * (0.5 + 1.5 * torch.stack([uniform(4 + j, g) for j in range(3)], -1))
    q = 2.0 * torch.stack([uniform(7 + j, g) for j in range(4)], -1) - 1.0
    qn = q.norm(dim=1, keepdim=True)
    quats = torch.where(qn > 1e-6, q / qn.clamp_min(1e-6), torch.tensor([1.0, 0.0, 0.0, 0.0]))
    opacities = 0.05 + 0.9 * uniform(11, g)
    base = torch.stack([0.5 + 0.4 * torch.sin(px.float() * 0.05 + py.float() * 0.03 + s.float() * 0.7 + ch)
                        for ch in range(3)], -1)
    k = torch.arange(25)
    deg = torch.floor(torch.sqrt(k.float())).long()  # degree of SH coefficient k
    amp = torch.where(deg == 0, torch.zeros(25), 0.1 * 0.25 ** deg.float())
    idx = g[:, None, None] * 75 + k[None, :, None] * 3 + torch.arange(3)[None, None, :]
    sh = amp[None, :, None] * (2.0 * uniform(12, idx) - 1.0)
    sh[:, 0, :] = (base - 0.5) / C0
    fidx = g[:, None] * n_features + torch.arange(n_features)[None, :]
    features = 2.0 * uniform(13, fidx) - 1.0
    render_c2w = look_at_origin(0.1, 0.0)
    viewmat = torch.linalg.inv(render_c2w)
    pix = torch.arange(height * width)[:, None]
    W1 = (2.0 * uniform(14, pix * 3 + torch.arange(3)) - 1.0).view(height, width, 3)
    W2 = (2.0 * uniform(15, pix * n_features + torch.arange(n_features)) - 1.0).view(height, width, n_features)
    return {"means": means, "scales": scales, "quats": quats, "opacities": opacities, "sh": sh,
            "features": features, "viewmatrix": viewmat, "intrinsics": (fx, fy, cx, cy),
            "background": torch.zeros(3), "W1": W1, "W2": W2}


# ----------------------------------------------------------------------------------------------------------------
# Fixture check and benchmark
# ----------------------------------------------------------------------------------------------------------------

def check_fixture(path: str, chunk: int) -> bool:
    from safetensors.torch import load_file

    fx_ = load_file(path)
    h, w = (int(v) for v in fx_["image_size"])
    params = {k: fx_[k].clone().requires_grad_(True) for k in ("means", "scales", "quats", "opacities", "sh",
                                                                 "features")}
    intr = tuple(float(v) for v in fx_["intrinsics"])
    out = rasterize(params["means"], params["scales"], params["quats"], params["opacities"], params["sh"],
                    params["features"], fx_["viewmatrix"], intr, w, h, fx_["background"], chunk=chunk)
    loss = (out["rgb"] * fx_["W1"]).sum() + (out["feat"] * fx_["W2"]).sum()
    loss.backward()
    ok = True
    for name in ("rgb", "feat", "alpha", "depth"):
        d = (out[name].detach() - fx_[name]).abs()
        e = d.max().item()
        n_over = int((d.reshape(h, w, -1).amax(-1) > 1e-4).sum())
        log(f"fixture {os.path.basename(path)}: {name:6s} max-abs {e:.3g} ({n_over} pixels > 1e-4)")
        ok &= e <= 1e-4
    radii_eq = torch.equal(out["radii"], fx_["radii"])
    log(f"fixture: radii identical: {radii_eq}; loss {loss.item():.6f} vs {fx_['loss'].item():.6f}")
    ok &= radii_eq
    # Gradients. This reference uses the true derivative (plus the feature stop-gradient); the fixture holds the
    # fork's backward, which differs (fixture README, "Loss and gradients" 2-5) in grad_sh[:,14] (quirk 5) and in the
    # geometry gradients (alpha clamp, Jacobian clamp, det^2+1e-7): those are printed for information only.
    keep = torch.ones(25, dtype=torch.bool)
    keep[14] = False
    for name, sel, strict in (("sh", keep, True), ("features", None, True), ("opacities", None, False),
                              ("means", None, False), ("scales", None, False), ("quats", None, False)):
        g, ref = params[name].grad, fx_[f"grad_{name}"]
        if sel is not None:
            g, ref = g[:, sel], ref[:, sel]
        e = (g - ref).abs().max().item() / max(ref.abs().max().item(), 1e-12)
        note = "(must be <= 1e-4)" if strict else "(info: the fork's backward is not the true derivative here)"
        log(f"fixture: grad_{name:9s}{' w/o coef 14' if sel is not None else ''} max-abs/max|ref| = {e:.3g} {note}")
        if strict:
            ok &= e <= 1e-4
    return ok


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=0, help="0 = 5 source views of W x H (573,440 at 448x256)")
    ap.add_argument("--width", type=int, default=448)
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--features", type=int, default=4)
    ap.add_argument("--threads", type=int, default=0, help="intra-op threads (0 = PyTorch default = all cores)")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--chunk", type=int, default=32, help="list entries composited per step (memory/speed knob)")
    ap.add_argument("--no-checkpoint", action="store_true",
                    help="keep every chunk's activations for backward (faster, memory ~ pairs x 256 pixels)")
    ap.add_argument("--check-fixture", metavar="FILE",
                    help="first validate against a rasterizer fixture (e.g. shared/fixtures/rasterizer/small"
                         ".safetensors): images max-abs <= 1e-4 and identical radii, else exit 1")
    ap.add_argument("--forward-only", action="store_true", help="skip the forward+backward timing")
    ap.add_argument("--scene-stats", action="store_true",
                    help="only generate the scene, project and bin it, print its statistics (cheap; no timing)")
    args = ap.parse_args()
    set_threads(args.threads)

    if args.check_fixture:
        if not check_fixture(args.check_fixture, args.chunk):
            sys.exit("fixture check FAILED")
        log("fixture check passed")

    n = args.gaussians or 5 * args.width * args.height
    sc = synthetic_scene(n, args.width, args.height, args.features)
    names = ("means", "scales", "quats", "opacities", "sh", "features")
    if args.scene_stats:
        fx, fy, cx, cy = sc["intrinsics"]
        with torch.no_grad():
            _, _, z, radii, rect, valid = project(sc["means"], sc["scales"], sc["quats"], sc["viewmatrix"], fx, fy,
                                                  cx, cy, args.width, args.height)
            gx = (args.width + TILE - 1) // TILE
            _, pair_t = bin_and_sort(rect[valid], z[valid], gx)
            counts = torch.bincount(pair_t, minlength=gx * ((args.height + TILE - 1) // TILE))
        emit({"bench": "raster_scene", "gaussians": n, "width": args.width, "height": args.height,
              "visible": int(valid.sum()), "tile_pairs": int(pair_t.numel()), "longest_tile_list": int(counts.max()),
              "mean_tile_list": round(float(counts.float().mean()), 1), "max_radius": int(radii.max()),
              "mean_radius_visible": round(float(radii[valid].float().mean()), 3),
              "checksum_means": round(float(sc["means"].double().sum()), 3),
              "checksum_sh": round(float(sc["sh"].double().sum()), 3)})
        return

    def run(grad: bool):
        params = [sc[k].clone().requires_grad_(grad) for k in names]
        with torch.set_grad_enabled(grad):
            out = rasterize(*params, sc["viewmatrix"], sc["intrinsics"], args.width, args.height, sc["background"],
                            chunk=args.chunk, checkpoint=not args.no_checkpoint)
            if grad:
                loss = (out["rgb"] * sc["W1"]).sum() + (out["feat"] * sc["W2"]).sum()
                loss.backward()
        return out

    stats = run(False)
    log(f"raster: {n} Gaussians, {stats['visible']} visible, {stats['pairs']} tile pairs, longest tile list "
        f"{stats['max_list']}, {torch.get_num_threads()} threads")
    fwd = time_ms(lambda: run(False), args.runs, warmup=0)  # the stats run above was the warm-up
    rec = {"bench": "raster", "gaussians": n, "width": args.width, "height": args.height, "features": args.features,
           "forward_ms": round(median(fwd), 3)}
    if not args.forward_only:
        fb = time_ms(lambda: run(True), args.runs, warmup=1)
        rec["forward_backward_ms"] = round(median(fb), 3)
        rec["forward_backward_runs_ms"] = [round(t, 3) for t in fb]
    rec.update({"forward_runs_ms": [round(t, 3) for t in fwd], "visible": stats["visible"],
                "tile_pairs": stats["pairs"], "threads": torch.get_num_threads(), "chunk": args.chunk,
                "checkpoint": not args.no_checkpoint, "peak_mib": round(peak_rss_mib(), 1),
                "torch": torch.__version__})
    emit(rec)


if __name__ == "__main__":
    main()
