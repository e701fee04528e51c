//! Tile kernels: front-to-back compositing (forward) and the reverse traversal (backward).
//!
//! Each tile loops over its depth-sorted Gaussians and, per Gaussian, over the pixels of a conservative
//! bounding box of its alpha ≥ 1/255 ellipse; per pixel the decisions are exactly the CUDA kernel's
//! (power > 0 skip, alpha < 1/255 skip, T·(1-alpha) < 1e-4 stop), so results match pixel-major order.

use rayon::prelude::*;

use super::binning::bin;
use super::preprocess::preprocess;
use super::{ForwardOutput, Frame, GradMode, PixelGrads, RasterInputs, RasterSettings, TILE};
use crate::error::{input_err, Result};
use crate::util::SharedMut;

const NPIX: usize = TILE * TILE;
const ALPHA_MIN: f32 = 1.0 / 255.0;

/// Per-tile copy of the data of its Gaussians (the CPU analogue of the kernel's shared memory).
#[derive(Default)]
struct Gathered {
    /// [mx, my, A, B, C, opacity, depth, unused] per Gaussian.
    geo: Vec<[f32; 8]>,
    col: Vec<f32>,
    feat: Vec<f32>,
}

impl Gathered {
    fn fill(&mut self, ids: &[u32], out: &ForwardOutput, inp: &RasterInputs, nf: usize) {
        self.geo.clear();
        self.col.clear();
        self.feat.clear();
        for &g in ids {
            let g = g as usize;
            self.geo.push([
                out.means2d[2 * g],
                out.means2d[2 * g + 1],
                out.conic[3 * g],
                out.conic[3 * g + 1],
                out.conic[3 * g + 2],
                inp.opacities[g],
                out.depths[g],
                0.0,
            ]);
            self.col.extend_from_slice(&out.colors[3 * g..3 * g + 3]);
            self.feat.extend_from_slice(&inp.features[nf * g..nf * g + nf]);
        }
    }
}

/// Inclusive pixel box (within the tile) that can hold alpha ≥ 1/255 for this Gaussian.
#[inline]
fn pixel_box(geo: &[f32; 8], x0: usize, x1: usize, y0: usize, y1: usize) -> Option<[usize; 4]> {
    let [mx, my, a, b, c, o, ..] = *geo;
    if !(o >= ALPHA_MIN) {
        return None;
    }
    let r2 = 2.0 * (255.0 * o).ln().max(0.0);
    let detq = a * c - b * b;
    let (ex, ey) = if detq > 0.0 && a > 0.0 && c > 0.0 {
        ((r2 * c / detq).sqrt() * 1.01 + 1.0, (r2 * a / detq).sqrt() * 1.01 + 1.0)
    } else {
        (f32::INFINITY, f32::INFINITY)
    };
    let lo = |m: f32, e: f32, lim: usize| -> f32 { (m - e).ceil().max(lim as f32) };
    let hi = |m: f32, e: f32, lim: usize| -> f32 { (m + e).floor().min(lim as f32 - 1.0) };
    let (xs, xe) = (lo(mx, ex, x0), hi(mx, ex, x1));
    let (ys, ye) = (lo(my, ey, y0), hi(my, ey, y1));
    // NaN bounds fall back to the whole tile.
    let xs = if xs.is_nan() { x0 as f32 } else { xs };
    let ys = if ys.is_nan() { y0 as f32 } else { ys };
    let xe = if xe.is_nan() { x1 as f32 - 1.0 } else { xe };
    let ye = if ye.is_nan() { y1 as f32 - 1.0 } else { ye };
    if xs > xe || ys > ye {
        return None;
    }
    Some([xs as usize, xe as usize, ys as usize, ye as usize])
}

/// exp(x) for x ≤ 0 (Cephes expf: ~1 ulp), written so the per-row loops auto-vectorise.
#[inline(always)]
pub(crate) fn fast_exp(x: f32) -> f32 {
    let x = x.clamp(-87.0, 88.0);
    let t = x * std::f32::consts::LOG2_E + 0.5;
    let mut fx = (t as i32) as f32;
    fx -= if fx > t { 1.0 } else { 0.0 };
    let r = x - fx * 0.693_359_4 + fx * 2.121_944_4e-4;
    let z = r * r;
    let y = (((((1.987_569_1e-4 * r + 1.398_199_9e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2) * r + 1.666_666_5e-1) * r
        + 5.000_000_1e-1)
        * z
        + r
        + 1.0;
    y * f32::from_bits(((fx as i32 + 127) as u32) << 23)
}

/// Conservative pixel span [xs, xe] of row `y` where alpha can reach 1/255; `None` if the row is missed.
#[inline(always)]
fn row_span(geo: &[f32; 8], r2: f32, y: usize, xs: usize, xe: usize) -> Option<(usize, usize)> {
    let [mx, my, a, b, c, ..] = *geo;
    let dy = my - y as f32;
    if !(a > 0.0 && a * c - b * b > 0.0) {
        return Some((xs, xe));
    }
    // A dx² + 2B dy dx + (C dy² - r2) ≤ 0 with dx = mx - x; r2 is inflated so rounding cannot lose a pixel.
    let disc = b * b * dy * dy - a * (c * dy * dy - r2);
    if disc < 0.0 {
        return None;
    }
    let sq = disc.sqrt();
    // r2 already carries the safety margin; 1e-3 px only absorbs rounding of the root.
    let lo = (mx - (-b * dy + sq) / a - 1e-3).ceil();
    let hi = (mx - (-b * dy - sq) / a + 1e-3).floor();
    let lo = if lo.is_nan() { xs as f32 } else { lo.max(xs as f32) };
    let hi = if hi.is_nan() { xe as f32 } else { hi.min(xe as f32) };
    if lo > hi {
        return None;
    }
    Some((lo as usize, hi as usize))
}

#[inline(always)]
fn inflated_r2(o: f32) -> f32 {
    2.0 * (255.0 * o).ln().max(0.0) * 1.02 + 0.02
}

fn tile_bounds(f: &Frame, t: usize) -> (usize, usize, usize, usize) {
    let (tx, ty) = (t % f.grid[0], t / f.grid[0]);
    let x0 = tx * TILE;
    let y0 = ty * TILE;
    (x0, (x0 + TILE).min(f.w), y0, (y0 + TILE).min(f.h))
}

struct FwdScratch {
    g: Gathered,
    t: [f32; NPIX],
    last: [u32; NPIX],
    done: [bool; NPIX],
    /// channel-major accumulators: rgb (3), depth (1), features (C)
    acc: Vec<f32>,
    abuf: [f32; TILE],
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
    let bins = bin(&f, &pre.means2d, &pre.radii, &pre.depths);
    let t2 = std::time::Instant::now();
    let hw = f.w * f.h;
    let mut out = ForwardOutput {
        width: f.w,
        height: f.h,
        num_features: nf,
        rgb: vec![0.0; 3 * hw],
        features: vec![0.0; nf * hw],
        alpha: vec![0.0; hw],
        depth: vec![0.0; hw],
        final_t: vec![0.0; hw],
        n_contrib: vec![0; hw],
        radii: pre.radii,
        tiles_touched: pre.tiles_touched,
        means2d: pre.means2d,
        cov2d: pre.cov2d,
        conic: pre.conic,
        depths: pre.depths,
        colors: pre.colors,
        clamped: pre.clamped,
        tile_start: bins.tile_start,
        point_list: bins.point_list,
    };
    let mut rgb = std::mem::take(&mut out.rgb);
    let mut feat = std::mem::take(&mut out.features);
    let mut alpha = std::mem::take(&mut out.alpha);
    let mut depth = std::mem::take(&mut out.depth);
    let mut final_t = std::mem::take(&mut out.final_t);
    let mut n_contrib = std::mem::take(&mut out.n_contrib);
    {
        let o_rgb = SharedMut::new(&mut rgb);
        let o_feat = SharedMut::new(&mut feat);
        let o_alpha = SharedMut::new(&mut alpha);
        let o_depth = SharedMut::new(&mut depth);
        let o_t = SharedMut::new(&mut final_t);
        let o_nc = SharedMut::new(&mut n_contrib);
        let outr = &out;
        let bg = s.background;
        (0..f.num_tiles()).into_par_iter().for_each_init(
            || FwdScratch {
                g: Gathered::default(),
                t: [1.0; NPIX],
                last: [0; NPIX],
                done: [false; NPIX],
                acc: vec![0.0; (4 + nf) * NPIX],
                abuf: [0.0; TILE],
            },
            |scr, t| {
                let (x0, x1, y0, y1) = tile_bounds(&f, t);
                let tw = x1 - x0;
                let np = tw * (y1 - y0);
                let ids = &outr.point_list[outr.tile_start[t] as usize..outr.tile_start[t + 1] as usize];
                scr.g.fill(ids, outr, inp, nf);
                scr.t[..np].fill(1.0);
                scr.last[..np].fill(0);
                scr.done[..np].fill(false);
                scr.acc.fill(0.0);
                let mut n_done = 0usize;
                for j in 0..ids.len() {
                    if n_done == np {
                        break;
                    }
                    let geo = &scr.g.geo[j];
                    let Some([xs, xe, ys, ye]) = pixel_box(geo, x0, x1, y0, y1) else { continue };
                    let col = &scr.g.col[3 * j..3 * j + 3];
                    let fe = &scr.g.feat[nf * j..nf * j + nf];
                    let o = geo[5];
                    let r2 = inflated_r2(o);
                    for y in ys..=ye {
                        let Some((rs, re)) = row_span(geo, r2, y, xs, xe) else { continue };
                        let len = re - rs + 1;
                        let dy = geo[1] - y as f32;
                        // Vectorisable pass: alpha of the whole span (0 where the kernel would skip on power > 0).
                        for (k, av) in scr.abuf[..len].iter_mut().enumerate() {
                            let dx = geo[0] - (rs + k) as f32;
                            let power = -0.5 * (geo[2] * dx * dx + geo[4] * dy * dy) - geo[3] * dx * dy;
                            let a = (o * fast_exp(power)).min(0.99);
                            *av = if power > 0.0 { 0.0 } else { a };
                        }
                        let row = (y - y0) * tw + rs - x0;
                        for k in 0..len {
                            let a = scr.abuf[k];
                            if a < ALPHA_MIN {
                                continue;
                            }
                            let lp = row + k;
                            if scr.done[lp] {
                                continue;
                            }
                            let tp = scr.t[lp];
                            let test_t = tp * (1.0 - a);
                            if test_t < 1e-4 {
                                scr.done[lp] = true;
                                n_done += 1;
                                continue;
                            }
                            let w = a * tp;
                            scr.acc[lp] += w * col[0];
                            scr.acc[NPIX + lp] += w * col[1];
                            scr.acc[2 * NPIX + lp] += w * col[2];
                            scr.acc[3 * NPIX + lp] += w * geo[6];
                            for (c, fv) in fe.iter().enumerate() {
                                scr.acc[(4 + c) * NPIX + lp] += w * fv;
                            }
                            scr.t[lp] = test_t;
                            scr.last[lp] = j as u32 + 1;
                        }
                    }
                }
                // SAFETY: tiles cover disjoint pixels.
                unsafe {
                    for y in y0..y1 {
                        for x in x0..x1 {
                            let lp = (y - y0) * tw + (x - x0);
                            let pix = y * f.w + x;
                            let tf = scr.t[lp];
                            for c in 0..3 {
                                o_rgb.write(c * hw + pix, scr.acc[c * NPIX + lp] + tf * bg[c]);
                            }
                            for c in 0..nf {
                                o_feat.write(c * hw + pix, scr.acc[(4 + c) * NPIX + lp]);
                            }
                            o_depth.write(pix, scr.acc[3 * NPIX + lp]);
                            o_alpha.write(pix, 1.0 - tf);
                            o_t.write(pix, tf);
                            o_nc.write(pix, scr.last[lp]);
                        }
                    }
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
            out.point_list.len()
        );
    }
    out.rgb = rgb;
    out.features = feat;
    out.alpha = alpha;
    out.depth = depth;
    out.final_t = final_t;
    out.n_contrib = n_contrib;
    Ok(out)
}

/// Channels of the per-pair gradient buffer (channel-major, `num_pairs` values each).
pub(crate) const P_MX: usize = 0;
pub(crate) const P_MY: usize = 1;
pub(crate) const P_CA: usize = 2;
pub(crate) const P_CB: usize = 3;
pub(crate) const P_CC: usize = 4;
pub(crate) const P_OP: usize = 5;
pub(crate) const P_COL: usize = 6;
pub(crate) const P_DEPTH: usize = 9;
pub(crate) const P_FEAT: usize = 10;

struct BwdScratch {
    g: Gathered,
    t: [f32; NPIX],
    tfin: [f32; NPIX],
    last: [u32; NPIX],
    bg_dot: [f32; NPIX],
    /// pixel grads, channel-major: rgb (3), alpha (1), depth (1), features (C)
    dpix: Vec<f32>,
    /// running Σ_{later} w·value, same channel order
    s: Vec<f32>,
    gbuf: [f32; TILE],
}

/// Reverse traversal per tile; returns the per-pair gradient buffer (channel-major).
pub(crate) fn backward_pairs(
    inp: &RasterInputs,
    s: &RasterSettings,
    fwd: &ForwardOutput,
    grads: &PixelGrads,
    mode: GradMode,
) -> Result<Vec<f32>> {
    let f = Frame::new(&s.camera);
    let nf = inp.num_features;
    let hw = f.w * f.h;
    if grads.rgb.len() != 3 * hw || grads.features.len() != nf * hw {
        return Err(input_err("pixel gradients", format!("expected 3x{hw} rgb and {nf}x{hw} feature values")));
    }
    let exact = mode == GradMode::Exact;
    let d_alpha = if exact { grads.alpha } else { None };
    let d_depth = if exact { grads.depth } else { None };
    for g in [d_alpha, d_depth].into_iter().flatten() {
        if g.len() != hw {
            return Err(input_err("pixel gradients", format!("alpha/depth gradients need {hw} values")));
        }
    }
    let np_total = fwd.point_list.len();
    let nch = P_FEAT + nf;
    let mut buf = vec![0f32; nch * np_total];
    let bs = SharedMut::new(&mut buf);
    let nchp = 5 + nf;
    let bg = s.background;
    (0..f.num_tiles()).into_par_iter().for_each_init(
        || BwdScratch {
            g: Gathered::default(),
            t: [0.0; NPIX],
            tfin: [0.0; NPIX],
            last: [0; NPIX],
            bg_dot: [0.0; NPIX],
            dpix: vec![0.0; nchp * NPIX],
            s: vec![0.0; nchp * NPIX],
            gbuf: [0.0; TILE],
        },
        |scr, t| {
            let (x0, x1, y0, y1) = tile_bounds(&f, t);
            let tw = x1 - x0;
            let start = fwd.tile_start[t] as usize;
            let ids = &fwd.point_list[start..fwd.tile_start[t + 1] as usize];
            let mut max_last = 0usize;
            scr.dpix.fill(0.0);
            scr.s.fill(0.0);
            for y in y0..y1 {
                for x in x0..x1 {
                    let lp = (y - y0) * tw + (x - x0);
                    let pix = y * f.w + x;
                    scr.t[lp] = fwd.final_t[pix];
                    scr.tfin[lp] = fwd.final_t[pix];
                    scr.last[lp] = fwd.n_contrib[pix];
                    max_last = max_last.max(fwd.n_contrib[pix] as usize);
                    let mut bd = 0f32;
                    for c in 0..3 {
                        let g = grads.rgb[c * hw + pix];
                        scr.dpix[c * NPIX + lp] = g;
                        bd += bg[c] * g;
                    }
                    scr.bg_dot[lp] = bd;
                    if let Some(a) = d_alpha {
                        scr.dpix[3 * NPIX + lp] = a[pix];
                    }
                    if let Some(d) = d_depth {
                        scr.dpix[4 * NPIX + lp] = d[pix];
                    }
                    for c in 0..nf {
                        scr.dpix[(5 + c) * NPIX + lp] = grads.features[c * hw + pix];
                    }
                }
            }
            if max_last == 0 {
                return;
            }
            scr.g.fill(&ids[..max_last], fwd, inp, nf);
            let mut accf = vec![0f32; nf];
            for j in (0..max_last).rev() {
                let geo = scr.g.geo[j];
                let Some([xs, xe, ys, ye]) = pixel_box(&geo, x0, x1, y0, y1) else { continue };
                let col = [scr.g.col[3 * j], scr.g.col[3 * j + 1], scr.g.col[3 * j + 2]];
                let fe = &scr.g.feat[nf * j..nf * j + nf];
                let (o, z) = (geo[5], geo[6]);
                let (mut g_mx, mut g_my, mut g_a, mut g_b, mut g_c, mut g_o) = (0f32, 0f32, 0f32, 0f32, 0f32, 0f32);
                let mut g_col = [0f32; 3];
                let mut g_z = 0f32;
                accf.fill(0.0);
                let mut any = false;
                let r2 = inflated_r2(o);
                for y in ys..=ye {
                    let Some((rs, re)) = row_span(&geo, r2, y, xs, xe) else { continue };
                    let len = re - rs + 1;
                    let dyr = geo[1] - y as f32;
                    for (k, gv) in scr.gbuf[..len].iter_mut().enumerate() {
                        let dx = geo[0] - (rs + k) as f32;
                        let power = -0.5 * (geo[2] * dx * dx + geo[4] * dyr * dyr) - geo[3] * dx * dyr;
                        *gv = if power > 0.0 { 0.0 } else { fast_exp(power) };
                    }
                    for k in 0..len {
                        let x = rs + k;
                        let lp = (y - y0) * tw + (x - x0);
                        if j as u32 >= scr.last[lp] {
                            continue;
                        }
                        let gk = scr.gbuf[k];
                        let raw = o * gk;
                        let a = raw.min(0.99);
                        if a < ALPHA_MIN {
                            continue;
                        }
                        let dx = geo[0] - x as f32;
                        let dy = dyr;
                        any = true;
                        let one_m = 1.0 - a;
                        let tp = scr.t[lp] / one_m;
                        scr.t[lp] = tp;
                        let w = a * tp;
                        let mut dl_da = 0f32;
                        for c in 0..3 {
                            let dp = scr.dpix[c * NPIX + lp];
                            g_col[c] += w * dp;
                            let sc = &mut scr.s[c * NPIX + lp];
                            dl_da += (col[c] * tp - *sc / one_m) * dp;
                            *sc += w * col[c];
                        }
                        dl_da += -scr.tfin[lp] / one_m * scr.bg_dot[lp];
                        for c in 0..nf {
                            let dp = scr.dpix[(5 + c) * NPIX + lp];
                            accf[c] += w * dp;
                        }
                        if exact {
                            for c in 0..nf {
                                let dp = scr.dpix[(5 + c) * NPIX + lp];
                                let sc = &mut scr.s[(5 + c) * NPIX + lp];
                                dl_da += (fe[c] * tp - *sc / one_m) * dp;
                                *sc += w * fe[c];
                            }
                            let da = scr.dpix[3 * NPIX + lp];
                            let sa = &mut scr.s[3 * NPIX + lp];
                            dl_da += (tp - *sa / one_m) * da;
                            *sa += w;
                            let dd = scr.dpix[4 * NPIX + lp];
                            let sd = &mut scr.s[4 * NPIX + lp];
                            dl_da += (z * tp - *sd / one_m) * dd;
                            *sd += w * z;
                            g_z += w * dd;
                        }
                        // Official: the 0.99 clamp is ignored in backward; exact: clamped alpha is constant.
                        let dl_dalpha = if exact && raw > 0.99 { 0.0 } else { dl_da };
                        let dl_dg = o * dl_dalpha;
                        let gdx = gk * dx;
                        let gdy = gk * dy;
                        let dg_ddelx = -gdx * geo[2] - gdy * geo[3];
                        let dg_ddely = -gdy * geo[4] - gdx * geo[3];
                        g_mx += dl_dg * dg_ddelx;
                        g_my += dl_dg * dg_ddely;
                        g_a += -0.5 * gdx * dx * dl_dg;
                        g_b += -0.5 * gdx * dy * dl_dg;
                        g_c += -0.5 * gdy * dy * dl_dg;
                        g_o += gk * dl_dalpha;
                    }
                }
                if !any {
                    continue;
                }
                let pi = start + j;
                // SAFETY: pair index pi belongs to this tile only.
                unsafe {
                    bs.write(P_MX * np_total + pi, g_mx);
                    bs.write(P_MY * np_total + pi, g_my);
                    bs.write(P_CA * np_total + pi, g_a);
                    bs.write(P_CB * np_total + pi, g_b);
                    bs.write(P_CC * np_total + pi, g_c);
                    bs.write(P_OP * np_total + pi, g_o);
                    for c in 0..3 {
                        bs.write((P_COL + c) * np_total + pi, g_col[c]);
                    }
                    bs.write(P_DEPTH * np_total + pi, g_z);
                    for c in 0..nf {
                        bs.write((P_FEAT + c) * np_total + pi, accf[c]);
                    }
                }
            }
        },
    );
    Ok(buf)
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
