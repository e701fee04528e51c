//! (tile, depth) sorted pair list: one global stable radix sort of the visible Gaussians by depth (ties keep
//! the index order), then a stable chunked counting sort by tile, so every tile list comes out depth-sorted.
//! Also records, per Gaussian, where each of its pairs landed (for the backward's deterministic reduction).

use rayon::prelude::*;

use super::preprocess::unpack_rect;
use super::Frame;
use crate::util::{Pooled, SharedMut, POOL_REC, POOL_U32};

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

/// A visible Gaussian in the depth sort: (depth bits << 32 | index, packed tile rect). Carrying the rect avoids
/// a random gather in depth order afterwards.
type Rec = [u64; 2];

/// Stable LSD radix sort of `v` by the upper 32 bits of the first word (11-bit digits, digits shared by all
/// keys skipped).
fn radix_sort_hi32(v: &mut Vec<Rec>) {
    const BITS: u32 = 11;
    const NB: usize = 1 << BITS;
    let n = v.len();
    if n < 2 {
        return;
    }
    let nch = num_chunks(n);
    let chunk = n.div_ceil(nch);
    let mut tmp = POOL_REC.take(n, [0; 2]);
    for pass in 0..3u32 {
        let shift = 32 + pass * BITS;
        let digit = |k: &Rec| ((k[0] >> shift) as usize) & (NB - 1);
        let src: &[Rec] = v;
        let hists: Vec<Vec<u32>> = src
            .par_chunks(chunk)
            .map(|c| {
                let mut h = vec![0u32; NB];
                for k in c {
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
            for k in c {
                let d = digit(k);
                // SAFETY: chunk c owns slots [offs[c][d], offs[c][d] + hist[c][d]) for every digit d.
                unsafe { dst.write(off[d] as usize, *k) };
                off[d] += 1;
            }
        });
        std::mem::swap(v, &mut tmp);
    }
    POOL_REC.put(tmp);
}

/// `rects`: per Gaussian, its tile rect packed by [`pack_rect`] (read only where `radii > 0`).
pub(crate) fn bin(f: &Frame, radii: &[i32], depths: &[f32], rects: &[u64]) -> Bins {
    let n = radii.len();
    let nt = f.num_tiles();
    // Depths of visible Gaussians are > 0.2, so their f32 bits order like the values.
    let mut recs = POOL_REC.take(0, [0; 2]);
    recs.reserve(n);
    for i in 0..n {
        if radii[i] > 0 {
            recs.push([((depths[i].to_bits() as u64) << 32) | i as u64, rects[i]]);
        }
    }
    radix_sort_hi32(&mut recs);
    let m = recs.len();
    let mut order = Pooled::new(POOL_U32.take(m, 0), &POOL_U32);
    for (o, r) in order.iter_mut().zip(recs.iter()) {
        *o = r[0] as u32;
    }

    let nch = num_chunks(m);
    let chunk = m.div_ceil(nch).max(1);
    let counts: Vec<Vec<u32>> = recs
        .par_chunks(chunk)
        .map(|rs| {
            let mut cnt = vec![0u32; nt];
            for r in rs {
                let t = unpack_rect(r[1]);
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
    for (p, r) in pstart.iter_mut().zip(recs.iter()) {
        *p = acc;
        let t = unpack_rect(r[1]);
        acc += ((t[2] - t[0]) * (t[3] - t[1])) as u32;
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
    recs.par_chunks(chunk).zip(pstart.par_chunks(chunk)).zip(cursors.par_iter_mut()).for_each(|((rs, ps), cur)| {
        for (r, &p0) in rs.iter().zip(ps) {
            let g = r[0] as u32;
            let t = unpack_rect(r[1]);
            let mut slot = p0;
            for ty in t[1]..t[3] {
                for tx in t[0]..t[2] {
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
    });
    POOL_REC.put(recs);
    Bins { tile_start, point_list, order, pstart, slot_of }
}

#[cfg(test)]
mod tests {
    use super::radix_sort_hi32;

    #[test]
    fn radix_sort_is_stable_and_sorted() {
        let mut x = 12345u64;
        let mut v: Vec<[u64; 2]> = (0..100_000u64)
            .map(|i| {
                x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                // Few distinct keys so ties are common.
                [((((x >> 40) % 5000) * 858_993) << 32) | i, x]
            })
            .collect();
        let mut want = v.clone();
        want.sort_by_key(|k| (k[0] >> 32, k[0] & 0xffff_ffff));
        radix_sort_hi32(&mut v);
        assert_eq!(v, want);
    }
}
