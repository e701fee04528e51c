//! (tile, depth) sorted pair list: one global stable radix sort of the visible Gaussians by depth (ties keep
//! the index order), then a stable chunked counting sort by tile, so every tile list comes out depth-sorted.
//! Also records, per Gaussian, where each of its pairs landed (for the backward's deterministic reduction).

use rayon::prelude::*;

use super::{tile_rect, Frame};
use crate::util::{Pooled, SharedMut, POOL_RECT, POOL_U32, POOL_U64};

pub(crate) struct Bins {
    /// len tiles + 1
    pub tile_start: Pooled<u32>,
    pub point_list: Pooled<u32>,
    /// Visible Gaussians in depth order (ties by index).
    pub order: Pooled<u32>,
    /// (M+1) start of each `order` entry's pairs in the Gaussian-major pair numbering.
    pub pstart: Pooled<u32>,
    /// Per position in `point_list`: its Gaussian-major slot (`pstart[m] + k`, k = row-major index of the
    /// tile in the Gaussian's tile rect).
    pub slot_of: Pooled<u32>,
}

/// Chunks for the parallel passes: enough for load balance, few enough for small histograms.
fn num_chunks(n: usize) -> usize {
    (n / 16_384).clamp(1, 4 * rayon::current_num_threads().max(1))
}

/// Stable LSD radix sort of `v` by the upper 32 bits (11-bit digits, digits shared by all keys skipped).
fn radix_sort_hi32(v: &mut Vec<u64>) {
    const BITS: u32 = 11;
    const NB: usize = 1 << BITS;
    let n = v.len();
    if n < 2 {
        return;
    }
    let nch = num_chunks(n);
    let chunk = n.div_ceil(nch);
    let mut tmp = POOL_U64.take(n, 0);
    for pass in 0..3u32 {
        let shift = 32 + pass * BITS;
        let digit = |k: u64| ((k >> shift) as usize) & (NB - 1);
        let src: &[u64] = v;
        let hists: Vec<Vec<u32>> = src
            .par_chunks(chunk)
            .map(|c| {
                let mut h = vec![0u32; NB];
                for &k in c {
                    h[digit(k)] += 1;
                }
                h
            })
            .collect();
        let mut total = vec![0usize; NB];
        for h in &hists {
            for (t, &x) in total.iter_mut().zip(h) {
                *t += x as usize;
            }
        }
        if total.iter().any(|&t| t == n) {
            continue;
        }
        let mut offs = vec![vec![0u32; NB]; hists.len()];
        let mut acc = 0u32;
        for d in 0..NB {
            for (c, h) in hists.iter().enumerate() {
                offs[c][d] = acc;
                acc += h[d];
            }
        }
        let dst = SharedMut::new(&mut tmp);
        src.par_chunks(chunk).zip(offs.par_iter_mut()).for_each(|(c, off)| {
            for &k in c {
                let d = digit(k);
                // SAFETY: chunk c owns slots [offs[c][d], offs[c][d] + hist[c][d]) for every digit d.
                unsafe { dst.write(off[d] as usize, k) };
                off[d] += 1;
            }
        });
        std::mem::swap(v, &mut tmp);
    }
    POOL_U64.put(tmp);
}

pub(crate) fn bin(f: &Frame, means2d: &[f32], radii: &[i32], depths: &[f32]) -> Bins {
    let n = radii.len();
    let nt = f.num_tiles();
    // Depths of visible Gaussians are > 0.2, so their f32 bits order like the values.
    let mut keys = POOL_U64.take(0, 0);
    keys.reserve(n);
    for i in 0..n {
        if radii[i] > 0 {
            keys.push(((depths[i].to_bits() as u64) << 32) | i as u64);
        }
    }
    radix_sort_hi32(&mut keys);
    let m = keys.len();
    let mut order = Pooled::new(POOL_U32.take(m, 0), &POOL_U32);
    for (o, &k) in order.iter_mut().zip(keys.iter()) {
        *o = k as u32;
    }
    POOL_U64.put(keys);

    let nch = num_chunks(m);
    let chunk = m.div_ceil(nch).max(1);
    // Tile rects in depth order (one random gather), tile counts per chunk.
    let mut rects = POOL_RECT.take(m, [0; 4]);
    let counts: Vec<Vec<u32>> = order
        .par_chunks(chunk)
        .zip(rects.par_chunks_mut(chunk))
        .map(|(ids, rs)| {
            let mut cnt = vec![0u32; nt];
            for (&g, r) in ids.iter().zip(rs.iter_mut()) {
                let g = g as usize;
                let t = tile_rect([means2d[2 * g], means2d[2 * g + 1]], radii[g], f.grid);
                *r = [t[0] as u32, t[1] as u32, t[2] as u32, t[3] as u32];
                for ty in t[1]..t[3] {
                    for tx in t[0]..t[2] {
                        cnt[ty * f.grid[0] + tx] += 1;
                    }
                }
            }
            cnt
        })
        .collect();
    let mut pstart = Pooled::new(POOL_U32.take(m + 1, 0), &POOL_U32);
    let mut acc = 0u32;
    for (p, r) in pstart.iter_mut().zip(rects.iter()) {
        *p = acc;
        acc += (r[2] - r[0]) * (r[3] - r[1]);
    }
    pstart[m] = acc;
    let total = acc as usize;
    let mut tile_start = Pooled::new(POOL_U32.take(nt + 1, 0), &POOL_U32);
    let mut cursors = vec![vec![0u32; nt]; counts.len()];
    let mut acc = 0u32;
    for t in 0..nt {
        tile_start[t] = acc;
        for (c, cnt) in counts.iter().enumerate() {
            cursors[c][t] = acc;
            acc += cnt[t];
        }
    }
    tile_start[nt] = acc;
    debug_assert_eq!(acc as usize, total);
    let mut point_list = Pooled::new(POOL_U32.take(total, 0), &POOL_U32);
    let mut slot_of = Pooled::new(POOL_U32.take(total, 0), &POOL_U32);
    let pl = SharedMut::new(&mut point_list);
    let so = SharedMut::new(&mut slot_of);
    let gw = f.grid[0];
    order.par_chunks(chunk).zip(rects.par_chunks(chunk)).zip(pstart.par_chunks(chunk)).zip(cursors.par_iter_mut()).for_each(
        |(((ids, rs), ps), cur)| {
            for ((&g, r), &p0) in ids.iter().zip(rs).zip(ps) {
                let mut slot = p0;
                for ty in r[1] as usize..r[3] as usize {
                    for tx in r[0] as usize..r[2] as usize {
                        let t = ty * gw + tx;
                        let pos = cur[t] as usize;
                        cur[t] += 1;
                        // SAFETY: chunk c owns slots [cursor_c[t], cursor_c[t] + count_c[t]) of every tile t.
                        unsafe {
                            pl.write(pos, g);
                            so.write(pos, slot);
                        }
                        slot += 1;
                    }
                }
            }
        },
    );
    POOL_RECT.put(rects);
    Bins { tile_start, point_list, order, pstart, slot_of }
}

#[cfg(test)]
mod tests {
    use super::radix_sort_hi32;

    #[test]
    fn radix_sort_is_stable_and_sorted() {
        let mut x = 12345u64;
        let mut v: Vec<u64> = (0..100_000u64)
            .map(|i| {
                x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                // Few distinct keys so ties are common.
                ((((x >> 40) % 5000) * 858_993) << 32) | i
            })
            .collect();
        let mut want = v.clone();
        want.sort_by_key(|k| (k >> 32, k & 0xffff_ffff));
        radix_sort_hi32(&mut v);
        assert_eq!(v, want);
    }
}
