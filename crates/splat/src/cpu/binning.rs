//! (tile, depth) sorted pair list: a chunked counting sort by tile (parallel, stable in Gaussian index),
//! then a per-tile sort by depth with the index as tie-break.

use rayon::prelude::*;

use super::{tile_rect, Frame};
use crate::util::SharedMut;

pub(crate) struct Bins {
    /// len tiles + 1
    pub tile_start: Vec<u32>,
    pub point_list: Vec<u32>,
}

pub(crate) fn bin(f: &Frame, means2d: &[f32], radii: &[i32], depths: &[f32]) -> Bins {
    let n = radii.len();
    let nt = f.num_tiles();
    let nchunks = (n / 8192).clamp(1, 64);
    let chunk = n.div_ceil(nchunks).max(1);
    let for_tiles = |i: usize, g: &mut dyn FnMut(usize)| {
        if radii[i] <= 0 {
            return;
        }
        let r = tile_rect([means2d[2 * i], means2d[2 * i + 1]], radii[i], f.grid);
        for ty in r[1]..r[3] {
            for tx in r[0]..r[2] {
                g(ty * f.grid[0] + tx);
            }
        }
    };
    let counts: Vec<Vec<u32>> = (0..nchunks)
        .into_par_iter()
        .map(|c| {
            let mut cnt = vec![0u32; nt];
            for i in c * chunk..((c + 1) * chunk).min(n) {
                for_tiles(i, &mut |t| cnt[t] += 1);
            }
            cnt
        })
        .collect();
    let mut tile_start = vec![0u32; nt + 1];
    let mut cursors = vec![vec![0u32; nt]; nchunks];
    let mut acc = 0u32;
    for t in 0..nt {
        tile_start[t] = acc;
        for c in 0..nchunks {
            cursors[c][t] = acc;
            acc += counts[c][t];
        }
    }
    tile_start[nt] = acc;
    let total = acc as usize;
    let mut keys = vec![0u64; total];
    let ks = SharedMut::new(&mut keys);
    cursors.par_iter_mut().enumerate().for_each(|(c, cur)| {
        for i in c * chunk..((c + 1) * chunk).min(n) {
            // Depths of visible Gaussians are > 0.2, so their f32 bits order like the values.
            let key = ((depths[i].to_bits() as u64) << 32) | i as u64;
            for_tiles(i, &mut |t| {
                // SAFETY: chunk c owns slots [cursor_c[t], cursor_c[t] + count_c[t]) of every tile t.
                unsafe { ks.write(cur[t] as usize, key) };
                cur[t] += 1;
            });
        }
    });
    // Per-tile depth sort.
    let mut slices: Vec<&mut [u64]> = Vec::with_capacity(nt);
    let mut rest: &mut [u64] = &mut keys;
    for t in 0..nt {
        let len = (tile_start[t + 1] - tile_start[t]) as usize;
        let (a, b) = rest.split_at_mut(len);
        slices.push(a);
        rest = b;
    }
    slices.par_iter_mut().for_each(|s| s.sort_unstable());
    let point_list: Vec<u32> = keys.par_iter().with_min_len(8192).map(|k| *k as u32).collect();
    Bins { tile_start, point_list }
}
