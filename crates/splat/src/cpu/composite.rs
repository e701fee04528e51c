//! Tile kernels: front-to-back compositing (forward) and the reverse traversal (backward).
//!
//! Gaussian-major inside a tile: per-pixel state (T, last contributor, accumulators) lives in a 16×16 scratch,
//! and each Gaussian visits only the rows / 8-pixel windows of the bounding box of its alpha ≥ 1/255 ellipse,
//! skipping finished pixels. Per pixel the decisions are exactly the CUDA kernel's (power > 0 skip,
//! alpha < 1/255 skip, T·(1-alpha) < 1e-4 stop) in the same depth order, so results equal the pixel-major loop.
//! The lane code is written once over [`F8`] and compiled for AVX2 (runtime-detected) and portably; both
//! give bit-identical results.

use rayon::prelude::*;

use super::binning::bin;
use super::preprocess::{preprocess, GEO_LEN};
use super::simd::{exp8, isa, Arr, Isa, F8, LANES};
use super::{ForwardOutput, Frame, GradMode, PixelGrads, RasterInputs, RasterSettings, TILE};
use crate::error::{input_err, Result};
use crate::util::SharedMut;

const NPIX: usize = TILE * TILE;
const ALPHA_MIN: f32 = 1.0 / 255.0;
/// Largest window start inside a tile row.
const WMAX: usize = TILE - LANES;

/// exp(x) as the kernels evaluate it (Cephes expf, ~1 ulp).
#[cfg(test)]
pub(crate) fn fast_exp(x: f32) -> f32 {
    super::simd::exp1(x)
}

fn tile_bounds(f: &Frame, t: usize) -> (usize, usize, usize, usize) {
    let (tx, ty) = (t % f.grid[0], t / f.grid[0]);
    let x0 = tx * TILE;
    let y0 = ty * TILE;
    (x0, (x0 + TILE).min(f.w), y0, (y0 + TILE).min(f.h))
}

/// Inclusive tile-local pixel box (xs, xe, ys, ye) that can hold alpha ≥ 1/255; `None` if empty.
#[inline(always)]
fn local_box(geo: &[f32; GEO_LEN], x0: usize, y0: usize, tw: usize, th: usize) -> Option<(usize, usize, usize, usize)> {
    let [mx, my, _, _, _, _, ex, ey] = *geo;
    let (x0f, y0f) = (x0 as f32, y0 as f32);
    // f32::max/min drop NaN, so NaN bounds fall back to the tile edges.
    let lx = (mx - ex).max(x0f).min(x0f + tw as f32).ceil();
    let hx = (mx + ex).min(x0f + tw as f32 - 1.0).max(x0f - 1.0).floor();
    let ly = (my - ey).max(y0f).min(y0f + th as f32).ceil();
    let hy = (my + ey).min(y0f + th as f32 - 1.0).max(y0f - 1.0).floor();
    if lx > hx || ly > hy {
        return None;
    }
    Some(((lx - x0f) as usize, (hx - x0f) as usize, (ly - y0f) as usize, (hy - y0f) as usize))
}

/// Lane range [lo, hi] (window-local, clamped to the window) of the pixels xs..=xe not yet handled, given
/// the window starts at `ws` and pixels before `s0` belong to the previous window.
#[inline(always)]
fn lane_range(ws: usize, s0: usize, xe: usize) -> (f32, f32) {
    ((s0 - ws) as f32, ((xe - ws).min(LANES - 1)) as f32)
}

/// Shared, read-only inputs of the tile kernels.
struct Ctx<'a> {
    f: &'a Frame,
    geo: &'a [[f32; GEO_LEN]],
    vals: &'a [f32],
    nv: usize,
    tile_start: &'a [u32],
    point_list: &'a [u32],
}

impl Ctx<'_> {
    #[inline(always)]
    fn ids(&self, t: usize) -> &[u32] {
        &self.point_list[self.tile_start[t] as usize..self.tile_start[t + 1] as usize]
    }

    #[inline(always)]
    fn prefetch(&self, ids: &[u32], j: usize) {
        #[cfg(target_arch = "x86_64")]
        if let Some(&g) = ids.get(j) {
            use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
            let g = g as usize;
            // SAFETY: prefetch never faults; the indices are in bounds anyway.
            unsafe {
                _mm_prefetch::<_MM_HINT_T0>(self.geo.as_ptr().add(g) as *const i8);
                _mm_prefetch::<_MM_HINT_T0>(self.vals.as_ptr().add(g * self.nv) as *const i8);
            }
        }
    }
}

struct FwdScratch {
    /// Transmittance; negated once the pixel is finished (so "live" is `t > 0`).
    t: [f32; NPIX],
    /// Last blended list position (1-based) as raw u32 bits.
    last: [f32; NPIX],
    /// Channel-major accumulators in `vals` order: r, g, b, depth, features.
    acc: Vec<f32>,
}

/// Planar output images of the forward pass.
struct FwdImages {
    rgb: SharedMut<f32>,
    feat: SharedMut<f32>,
    alpha: SharedMut<f32>,
    depth: SharedMut<f32>,
    final_t: SharedMut<f32>,
    n_contrib: SharedMut<u32>,
    bg: [f32; 3],
}

#[inline(always)]
unsafe fn fwd_tile<V: F8>(c: &Ctx, tile: usize, s: &mut FwdScratch, out: &FwdImages) {
    let f = c.f;
    let (x0, x1, y0, y1) = tile_bounds(f, tile);
    let (tw, th) = (x1 - x0, y1 - y0);
    let nv = c.nv;
    s.t.fill(1.0);
    s.last.fill(0.0);
    s.acc[..nv * NPIX].fill(0.0);
    let mut live = [0u32; TILE];
    for l in live.iter_mut().take(th) {
        *l = (1u32 << tw) - 1;
    }
    let mut live_rows = th;
    let ids = c.ids(tile);
    let (zero, one) = (V::splat(0.0), V::splat(1.0));
    let (amin, amax, tmin) = (V::splat(ALPHA_MIN), V::splat(0.99), V::splat(1e-4));
    let sign = V::splat(-0.0);
    let iota = V::iota();
    let tp = s.t.as_mut_ptr();
    let lp = s.last.as_mut_ptr();
    let ap = s.acc.as_mut_ptr();
    for (j, &g) in ids.iter().enumerate() {
        if live_rows == 0 {
            break;
        }
        c.prefetch(ids, j + 8);
        let g = g as usize;
        let geo = &c.geo[g];
        let Some((xs, xe, ys, ye)) = local_box(geo, x0, y0, tw, th) else {
            continue;
        };
        let span = ((1u32 << (xe + 1)) - 1) & !((1u32 << xs) - 1);
        let [mx, my, ca, cb, cc, o, ..] = *geo;
        let vals = &c.vals[g * nv..g * nv + nv];
        let (mxv, cav, ov) = (V::splat(mx), V::splat(ca), V::splat(o));
        let jv = V::splat(f32::from_bits(j as u32 + 1));
        for ly in ys..=ye {
            if live[ly] & span == 0 {
                continue;
            }
            let dy = my - (y0 + ly) as f32;
            let (cdy2, bdy) = (V::splat(cc * dy * dy), V::splat(cb * dy));
            let mut s0 = xs;
            while s0 <= xe {
                let ws = s0.min(WMAX);
                let (lo, hi) = lane_range(ws, s0, xe);
                s0 = ws + LANES;
                if (live[ly] >> ws) & 0xff == 0 {
                    continue;
                }
                let idx = ly * TILE + ws;
                let dx = mxv.sub(V::splat((x0 + ws) as f32).add(iota));
                let power = V::splat(-0.5).mul(cav.mul(dx).mul(dx).add(cdy2)).sub(dx.mul(bdy));
                let al = ov.mul(exp8(power)).min(amax);
                let tv = V::load(tp.add(idx));
                let act = iota.ge(V::splat(lo)).and(iota.le(V::splat(hi))).and(power.le(zero)).and(al.ge(amin)).and(tv.gt(zero));
                if act.bits() == 0 {
                    continue;
                }
                let test = tv.mul(one.sub(al));
                let stop = act.and(test.lt(tmin));
                let blend = act.and_not(stop);
                V::select(blend, test, V::select(stop, tv.xor(sign), tv)).store(tp.add(idx));
                let sb = stop.bits();
                if sb != 0 {
                    live[ly] &= !(sb << ws);
                    if live[ly] == 0 {
                        live_rows -= 1;
                    }
                }
                if blend.bits() == 0 {
                    continue;
                }
                V::select(blend, jv, V::load(lp.add(idx))).store(lp.add(idx));
                let w = al.mul(tv).and(blend);
                for (ch, &v) in vals.iter().enumerate() {
                    let p = ap.add(ch * NPIX + idx);
                    V::load(p).add(w.mul(V::splat(v))).store(p);
                }
            }
        }
    }
    let hw = f.w * f.h;
    let nf = nv - 4;
    for ly in 0..th {
        for lx in 0..tw {
            let l = ly * TILE + lx;
            let pix = (y0 + ly) * f.w + x0 + lx;
            let tf = s.t[l].abs();
            for ch in 0..3 {
                out.rgb.write(ch * hw + pix, s.acc[ch * NPIX + l] + tf * out.bg[ch]);
            }
            out.depth.write(pix, s.acc[3 * NPIX + l]);
            for ch in 0..nf {
                out.feat.write(ch * hw + pix, s.acc[(4 + ch) * NPIX + l]);
            }
            out.alpha.write(pix, 1.0 - tf);
            out.final_t.write(pix, tf);
            out.n_contrib.write(pix, s.last[l].to_bits());
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn fwd_tile_avx2(c: &Ctx, tile: usize, s: &mut FwdScratch, out: &FwdImages) {
    fwd_tile::<super::simd::Avx>(c, tile, s, out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,avx512f,avx512vl")]
unsafe fn fwd_tile_avx512(c: &Ctx, tile: usize, s: &mut FwdScratch, out: &FwdImages) {
    fwd_tile::<super::simd::Avx>(c, tile, s, out)
}

unsafe fn fwd_tile_portable(c: &Ctx, tile: usize, s: &mut FwdScratch, out: &FwdImages) {
    fwd_tile::<Arr>(c, tile, s, out)
}

/// Forward rasterization of one view.
pub fn forward(inp: &RasterInputs, s: &RasterSettings) -> Result<ForwardOutput> {
    inp.validate()?;
    s.camera.validate()?;
    let f = Frame::new(&s.camera);
    let nf = inp.num_features;
    let timing = std::env::var_os("MVSPLAT360_RASTER_TIMING").is_some();
    let t0 = std::time::Instant::now();
    let pre = preprocess(&f, inp);
    let t1 = std::time::Instant::now();
    let bins = bin(&f, &pre.radii, &pre.depths, &pre.rects);
    let t2 = std::time::Instant::now();
    let hw = f.w * f.h;
    let mut rgb = vec![0.0; 3 * hw];
    let mut feat = vec![0.0; nf * hw];
    let mut alpha = vec![0.0; hw];
    let mut depth = vec![0.0; hw];
    let mut final_t = vec![0.0; hw];
    let mut n_contrib = vec![0; hw];
    {
        let imgs = FwdImages {
            rgb: SharedMut::new(&mut rgb),
            feat: SharedMut::new(&mut feat),
            alpha: SharedMut::new(&mut alpha),
            depth: SharedMut::new(&mut depth),
            final_t: SharedMut::new(&mut final_t),
            n_contrib: SharedMut::new(&mut n_contrib),
            bg: s.background,
        };
        let ctx = Ctx { f: &f, geo: &pre.geo, vals: &pre.vals, nv: 4 + nf, tile_start: &bins.tile_start, point_list: &bins.point_list };
        let isa = isa();
        (0..f.num_tiles()).into_par_iter().for_each_init(
            || FwdScratch { t: [0.0; NPIX], last: [0.0; NPIX], acc: vec![0.0; (4 + nf) * NPIX] },
            |scr, t| {
                // SAFETY: tiles write disjoint pixels; each ISA only where detected.
                unsafe {
                    #[cfg(target_arch = "x86_64")]
                    match isa {
                        Isa::Avx512 => return fwd_tile_avx512(&ctx, t, scr, &imgs),
                        Isa::Avx2 => return fwd_tile_avx2(&ctx, t, scr, &imgs),
                        Isa::Portable => {}
                    }
                    fwd_tile_portable(&ctx, t, scr, &imgs)
                }
            },
        );
    }
    if timing {
        eprintln!(
            "raster forward: preprocess {:.1} ms, binning {:.1} ms, composite {:.1} ms ({} pairs)",
            (t1 - t0).as_secs_f64() * 1e3,
            (t2 - t1).as_secs_f64() * 1e3,
            t2.elapsed().as_secs_f64() * 1e3,
            bins.point_list.len()
        );
    }
    Ok(ForwardOutput {
        width: f.w,
        height: f.h,
        num_features: nf,
        rgb,
        features: feat,
        alpha,
        depth,
        final_t,
        n_contrib,
        radii: pre.radii,
        tiles_touched: pre.tiles_touched,
        means2d: pre.means2d,
        cov2d: pre.cov2d,
        conic: pre.conic,
        depths: pre.depths,
        colors: pre.colors,
        clamped: pre.clamped,
        geo: pre.geo,
        vals: pre.vals,
        tile_start: bins.tile_start,
        point_list: bins.point_list,
        order: bins.order,
        pstart: bins.pstart,
        slot_of: bins.slot_of,
    })
}

/// Channels of one row of the pair-major gradient buffer (`pair_stride` values per pair).
pub(crate) const P_MX: usize = 0;
pub(crate) const P_MY: usize = 1;
pub(crate) const P_CA: usize = 2;
pub(crate) const P_CB: usize = 3;
pub(crate) const P_CC: usize = 4;
pub(crate) const P_OP: usize = 5;
/// Then the `vals` channels: r, g, b, depth, features.
pub(crate) const P_COL: usize = 6;
pub(crate) const P_DEPTH: usize = 9;
pub(crate) const P_FEAT: usize = 10;

/// Values per pair in the gradient buffer.
pub(crate) fn pair_stride(nf: usize) -> usize {
    P_FEAT + nf
}

struct BwdScratch {
    t: [f32; NPIX],
    /// -T_final
    ntfin: [f32; NPIX],
    /// n_contrib as raw u32 bits
    last: [f32; NPIX],
    bg_dot: [f32; NPIX],
    /// Pixel grads, channel-major in `vals` order plus alpha last: r, g, b, depth, features, alpha.
    dpix: Vec<f32>,
    /// Running Σ_{later} w·value, same channel order.
    s: Vec<f32>,
    /// Per-Gaussian lane accumulators of w·dpix, one vector per `vals` channel.
    gacc: Vec<f32>,
}

struct BwdCtx<'a> {
    c: Ctx<'a>,
    fwd: &'a ForwardOutput,
    grads: &'a PixelGrads<'a>,
    d_alpha: Option<&'a [f32]>,
    d_depth: Option<&'a [f32]>,
    exact: bool,
    bg: [f32; 3],
    buf: SharedMut<f32>,
    ps: usize,
}

#[inline(always)]
unsafe fn bwd_tile<V: F8>(b: &BwdCtx, tile: usize, s: &mut BwdScratch) {
    let c = &b.c;
    let f = c.f;
    let fwd = b.fwd;
    let (x0, x1, y0, y1) = tile_bounds(f, tile);
    let (tw, th) = (x1 - x0, y1 - y0);
    let nv = c.nv;
    let nch = nv + 1;
    let hw = f.w * f.h;
    let start = c.tile_start[tile] as usize;
    let ids = c.ids(tile);
    let ps = b.ps;
    s.last.fill(0.0);
    s.t.fill(0.0);
    s.ntfin.fill(0.0);
    s.bg_dot.fill(0.0);
    s.dpix[..nch * NPIX].fill(0.0);
    s.s[..nch * NPIX].fill(0.0);
    let mut row_max = [0u32; TILE];
    for ly in 0..th {
        for lx in 0..tw {
            let l = ly * TILE + lx;
            let pix = (y0 + ly) * f.w + x0 + lx;
            let tf = fwd.final_t[pix];
            s.t[l] = tf;
            s.ntfin[l] = -tf;
            let nc = fwd.n_contrib[pix];
            s.last[l] = f32::from_bits(nc);
            row_max[ly] = row_max[ly].max(nc);
            let mut bd = 0f32;
            for ch in 0..3 {
                let gv = b.grads.rgb[ch * hw + pix];
                s.dpix[ch * NPIX + l] = gv;
                bd += b.bg[ch] * gv;
            }
            s.bg_dot[l] = bd;
            if let Some(d) = b.d_depth {
                s.dpix[3 * NPIX + l] = d[pix];
            }
            for ch in 0..nv - 4 {
                s.dpix[(4 + ch) * NPIX + l] = b.grads.features[ch * hw + pix];
            }
            if let Some(a) = b.d_alpha {
                s.dpix[nv * NPIX + l] = a[pix];
            }
        }
    }
    let max_last = (row_max.iter().copied().max().unwrap_or(0) as usize).min(ids.len());
    // Pairs no pixel blended get zero rows (the buffer is reused, not zeroed).
    let slots = &fwd.slot_of[start..start + ids.len()];
    for &sl in &slots[max_last..] {
        for k in 0..ps {
            b.buf.write(sl as usize * ps + k, 0.0);
        }
    }
    // Channels entering dL/dalpha: official = rgb only (features are stop-grad); exact = all incl. alpha.
    let n_dl = if b.exact { nch } else { 3 };
    let (zero, one) = (V::splat(0.0), V::splat(1.0));
    let (amin, amax) = (V::splat(ALPHA_MIN), V::splat(0.99));
    let half = V::splat(-0.5);
    let iota = V::iota();
    let tp = s.t.as_mut_ptr();
    let lp = s.last.as_ptr();
    let dp = s.dpix.as_ptr();
    let sp = s.s.as_mut_ptr();
    let gp = s.gacc.as_mut_ptr();
    for j in (0..max_last).rev() {
        if j >= 8 {
            c.prefetch(ids, j - 8);
        }
        let g = ids[j] as usize;
        let geo = &c.geo[g];
        let row = slots[j] as usize * ps;
        let Some((xs, xe, ys, ye)) = local_box(geo, x0, y0, tw, th) else {
            for k in 0..ps {
                b.buf.write(row + k, 0.0);
            }
            continue;
        };
        let [mx, my, ca, cb, cc, o, ..] = *geo;
        let vals = &c.vals[g * nv..g * nv + nv];
        let (mxv, cav, cbv, ccv, ov) = (V::splat(mx), V::splat(ca), V::splat(cb), V::splat(cc), V::splat(o));
        let jv = V::splat(f32::from_bits(j as u32));
        let (mut g_mx, mut g_my, mut g_a, mut g_b, mut g_c, mut g_o) = (zero, zero, zero, zero, zero, zero);
        for ch in 0..nv {
            zero.store(gp.add(ch * LANES));
        }
        let mut any = false;
        for ly in ys..=ye {
            if (j as u32) >= row_max[ly] {
                continue;
            }
            let dy = my - (y0 + ly) as f32;
            let dyv = V::splat(dy);
            let (cdy2, bdy) = (V::splat(cc * dy * dy), V::splat(cb * dy));
            let mut s0 = xs;
            while s0 <= xe {
                let ws = s0.min(WMAX);
                let (lo, hi) = lane_range(ws, s0, xe);
                s0 = ws + LANES;
                let idx = ly * TILE + ws;
                let dx = mxv.sub(V::splat((x0 + ws) as f32).add(iota));
                let power = half.mul(cav.mul(dx).mul(dx).add(cdy2)).sub(dx.mul(bdy));
                let gk = exp8(power);
                let raw = ov.mul(gk);
                let a = raw.min(amax);
                let act = iota.ge(V::splat(lo)).and(iota.le(V::splat(hi))).and(power.le(zero)).and(a.ge(amin)).and(V::load(lp.add(idx)).gt_i32(jv));
                if act.bits() == 0 {
                    continue;
                }
                any = true;
                let inv = one.div(one.sub(a));
                let tv = V::load(tp.add(idx));
                let tpv = V::select(act, tv.mul(inv), tv);
                tpv.store(tp.add(idx));
                let w = a.mul(tpv).and(act);
                let mut dl = V::load(s.ntfin.as_ptr().add(idx)).mul(inv).mul(V::load(s.bg_dot.as_ptr().add(idx)));
                for ch in 0..n_dl {
                    // The alpha channel's value is 1.
                    let v = V::splat(if ch < nv { vals[ch] } else { 1.0 });
                    let d = V::load(dp.add(ch * NPIX + idx));
                    let sv = V::load(sp.add(ch * NPIX + idx));
                    dl = dl.add(v.mul(tpv).sub(sv.mul(inv)).mul(d));
                    sv.add(w.mul(v)).store(sp.add(ch * NPIX + idx));
                }
                for ch in 0..nv {
                    if ch == 3 && !b.exact {
                        continue;
                    }
                    let d = V::load(dp.add(ch * NPIX + idx));
                    let q = gp.add(ch * LANES);
                    V::load(q).add(w.mul(d)).store(q);
                }
                // Official: the 0.99 clamp is ignored in backward; exact: a clamped alpha is constant.
                let mut dla = dl.and(act);
                if b.exact {
                    dla = dla.and_not(raw.gt(amax));
                }
                let gm = gk.and(act);
                let dl_dg = ov.mul(dla);
                let gdx = gm.mul(dx);
                let gdy = gm.mul(dyv);
                let dg_ddelx = zero.sub(gdx.mul(cav)).sub(gdy.mul(cbv));
                let dg_ddely = zero.sub(gdy.mul(ccv)).sub(gdx.mul(cbv));
                g_mx = g_mx.add(dl_dg.mul(dg_ddelx));
                g_my = g_my.add(dl_dg.mul(dg_ddely));
                g_a = g_a.add(half.mul(gdx).mul(dx).mul(dl_dg));
                g_b = g_b.add(half.mul(gdx).mul(dyv).mul(dl_dg));
                g_c = g_c.add(half.mul(gdy).mul(dyv).mul(dl_dg));
                g_o = g_o.add(gm.mul(dla));
            }
        }
        if !any {
            for k in 0..ps {
                b.buf.write(row + k, 0.0);
            }
            continue;
        }
        for (k, v) in [g_mx, g_my, g_a, g_b, g_c, g_o].into_iter().enumerate() {
            b.buf.write(row + k, v.hsum());
        }
        for ch in 0..nv {
            b.buf.write(row + P_COL + ch, V::load(gp.add(ch * LANES)).hsum());
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,avx512f,avx512vl")]
unsafe fn bwd_tile_avx512(b: &BwdCtx, tile: usize, s: &mut BwdScratch) {
    bwd_tile::<super::simd::Avx>(b, tile, s)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn bwd_tile_avx2(b: &BwdCtx, tile: usize, s: &mut BwdScratch) {
    bwd_tile::<super::simd::Avx>(b, tile, s)
}

unsafe fn bwd_tile_portable(b: &BwdCtx, tile: usize, s: &mut BwdScratch) {
    bwd_tile::<Arr>(b, tile, s)
}

/// Reverse traversal per tile; fills `buf` (one row of [`pair_stride`] values per pair, in the Gaussian-major
/// slot order of `slot_of`) completely.
pub(crate) fn backward_pairs(
    inp: &RasterInputs,
    s: &RasterSettings,
    fwd: &ForwardOutput,
    grads: &PixelGrads,
    mode: GradMode,
    buf: &mut Vec<f32>,
) -> Result<()> {
    let f = Frame::new(&s.camera);
    let nf = inp.num_features;
    let hw = f.w * f.h;
    if grads.rgb.len() != 3 * hw || grads.features.len() != nf * hw {
        return Err(input_err("pixel gradients", format!("expected 3x{hw} rgb and {nf}x{hw} feature values")));
    }
    if fwd.num_features != nf || fwd.vals.len() != (4 + nf) * inp.len() {
        return Err(input_err("forward output", "does not belong to these inputs (rerun forward)"));
    }
    let exact = mode == GradMode::Exact;
    let d_alpha = if exact { grads.alpha } else { None };
    let d_depth = if exact { grads.depth } else { None };
    for g in [d_alpha, d_depth].into_iter().flatten() {
        if g.len() != hw {
            return Err(input_err("pixel gradients", format!("alpha/depth gradients need {hw} values")));
        }
    }
    let ps = pair_stride(nf);
    let len = ps * fwd.point_list.len();
    // Every row is written by its tile, so a reused buffer needs no zeroing.
    buf.resize(len, 0.0);
    buf.truncate(len);
    let nv = 4 + nf;
    let bc = BwdCtx {
        c: Ctx { f: &f, geo: &fwd.geo, vals: &fwd.vals, nv, tile_start: &fwd.tile_start, point_list: &fwd.point_list },
        fwd,
        grads,
        d_alpha,
        d_depth,
        exact,
        bg: s.background,
        buf: SharedMut::new(buf),
        ps,
    };
    let isa = isa();
    (0..f.num_tiles()).into_par_iter().for_each_init(
        || BwdScratch {
            t: [0.0; NPIX],
            ntfin: [0.0; NPIX],
            last: [0.0; NPIX],
            bg_dot: [0.0; NPIX],
            dpix: vec![0.0; (nv + 1) * NPIX],
            s: vec![0.0; (nv + 1) * NPIX],
            gacc: vec![0.0; nv * LANES],
        },
        |scr, t| {
            // SAFETY: each tile writes only its own pair rows; each ISA only where detected.
            unsafe {
                #[cfg(target_arch = "x86_64")]
                match isa {
                    Isa::Avx512 => return bwd_tile_avx512(&bc, t, scr),
                    Isa::Avx2 => return bwd_tile_avx2(&bc, t, scr),
                    Isa::Portable => {}
                }
                bwd_tile_portable(&bc, t, scr)
            }
        },
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::fast_exp;

    #[test]
    fn fast_exp_is_accurate_on_the_rasterizer_range() {
        let mut worst = 0f64;
        for i in 0..=200_000 {
            let x = -30.0 * i as f32 / 200_000.0;
            let want = (x as f64).exp();
            worst = worst.max(((fast_exp(x) as f64) - want).abs() / want);
        }
        assert!(worst < 3e-7, "relative error {worst:.3e}");
        assert_eq!(fast_exp(0.0), 1.0);
        assert!(fast_exp(-200.0) >= 0.0 && fast_exp(-200.0) < 1e-37);
    }
}

#[cfg(test)]
mod simd_paths {
    use crate::bench::synthetic_scene;
    use crate::cpu::simd::{isa, set_max_isa, Isa, ISA_TEST_LOCK};
    use crate::cpu::{backward, forward, GradMode, PixelGrads, RasterSettings};

    /// The AVX-512VL, AVX2 and portable kernels must agree bit for bit (same operations, no FMA contraction),
    /// and repeated runs must be identical (determinism).
    #[test]
    fn isa_variants_agree_bitwise() {
        let _lock = ISA_TEST_LOCK.lock().unwrap_or_else(|e| e.into_inner());
        let sc = synthetic_scene(3 * 40 * 24, 40, 24, 3);
        let inp = sc.inputs();
        let st = RasterSettings { camera: sc.camera, background: [0.2, 0.4, 0.6] };
        let hw = 40 * 24;
        let ones = vec![0.5f32; hw];
        // Each run records the instruction set the kernels dispatched to (the cap only lowers it), so the
        // comparisons below are between code paths that really differ, not one path run twice.
        let run = |max: Isa, mode: GradMode| {
            set_max_isa(max);
            let ran = isa();
            let out = forward(&inp, &st).unwrap();
            let pg = PixelGrads { rgb: &sc.w1, features: &sc.w2, alpha: Some(&ones), depth: Some(&ones) };
            let g = backward(&inp, &st, &out, &pg, mode).unwrap();
            set_max_isa(Isa::Avx512);
            (ran, out, g)
        };
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let mut ran_paths = Vec::new();
        for mode in [GradMode::Official, GradMode::Exact] {
            let (isa_a, a, ga) = run(Isa::Avx512, mode);
            let (_, a2, ga2) = run(Isa::Avx512, mode);
            assert!(a.n_contrib.iter().any(|&c| c > 0), "scene renders nothing");
            // Determinism: the same path twice.
            assert_eq!(bits(&a.rgb), bits(&a2.rgb));
            assert_eq!(bits(&ga.means), bits(&ga2.means));
            ran_paths = vec![isa_a];
            for max in [Isa::Avx2, Isa::Portable] {
                let (isa_b, b, gb) = run(max, mode);
                if ran_paths.contains(&isa_b) {
                    continue; // capped to a path already compared (e.g. no AVX-512 here)
                }
                ran_paths.push(isa_b);
                let what = format!("{isa_a:?} vs {isa_b:?}, {mode:?}");
                assert_eq!(bits(&a.rgb), bits(&b.rgb), "rgb {what}");
                assert_eq!(bits(&a.features), bits(&b.features), "features {what}");
                assert_eq!(bits(&a.depth), bits(&b.depth), "depth {what}");
                assert_eq!(bits(&a.final_t), bits(&b.final_t), "final_T {what}");
                assert_eq!(a.n_contrib, b.n_contrib, "n_contrib {what}");
                assert_eq!(bits(&ga.means), bits(&gb.means), "grad means {what}");
                assert_eq!(bits(&ga.opacities), bits(&gb.opacities), "grad opacities {what}");
                assert_eq!(bits(&ga.cov3d), bits(&gb.cov3d), "grad cov3d {what}");
                assert_eq!(bits(&ga.sh), bits(&gb.sh), "grad sh {what}");
                assert_eq!(bits(&ga.features), bits(&gb.features), "grad features {what}");
            }
        }
        eprintln!("compared instruction sets: {ran_paths:?}");
        // Portable always runs; on x86-64 with AVX2+FMA a vector path must have run beside it, else this test
        // compared nothing.
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
            assert!(ran_paths.len() >= 2 && ran_paths.contains(&Isa::Portable), "only {ran_paths:?} ran");
        }
    }
}
