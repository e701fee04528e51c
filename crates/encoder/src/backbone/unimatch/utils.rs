//! Window split/merge for Swin-style attention and the shifted-window mask (UniMatch `utils.py`).

use candle_core::{Device, Result, Tensor};

/// `[N, h, w, c]` → `[N·K·K, (h/K)·(w/K), c]`, windows ordered row-major per image (`split_feature`,
/// channel-last).
pub fn split_windows(x: &Tensor, k: usize) -> Result<Tensor> {
    let (n, h, w, c) = x.dims4()?;
    let (hs, ws) = (h / k, w / k);
    x.reshape((n, k, hs, k, ws, c))?.permute((0, 1, 3, 2, 4, 5))?.reshape((n * k * k, hs * ws, c))
}

/// Inverse of [`split_windows`]: `[N·K·K, (h/K)·(w/K), c]` → `[N, h, w, c]`.
pub fn merge_windows(x: &Tensor, k: usize, h: usize, w: usize) -> Result<Tensor> {
    let (nkk, _, c) = x.dims3()?;
    let n = nkk / (k * k);
    let (hs, ws) = (h / k, w / k);
    x.reshape((n, k, k, hs, ws, c))?.permute((0, 1, 3, 2, 4, 5))?.reshape((n, h, w, c))
}

/// Region label per pixel of the shifted map (Swin's `img_mask`): 3×3 regions split at `-window`, `-shift`.
fn region_labels(h: usize, w: usize, wh: usize, ww: usize, sh: usize, sw: usize) -> Vec<u32> {
    let band = |i: usize, n: usize, win: usize, s: usize| -> u32 {
        if i < n - win {
            0
        } else if i < n - s {
            1
        } else {
            2
        }
    };
    let mut m = vec![0u32; h * w];
    for y in 0..h {
        for x in 0..w {
            m[y * w + x] = band(y, h, wh, sh) * 3 + band(x, w, ww, sw);
        }
    }
    m
}

/// Region labels behind [`shifted_window_mask`]: `(q [K·K, Lw], k [K·K, m·Lw])`; mask entry `(win, i, j)` is −100
/// exactly where `q[win][i] != k[win][j]`.
pub fn shifted_window_labels(h: usize, w: usize, k: usize, m: usize) -> (Vec<u8>, Vec<u8>) {
    let (wh, ww) = (h / k, w / k);
    let (sh, sw) = (wh / 2, ww / 2);
    let labels = region_labels(h, w, wh, ww, sh, sw);
    let lw = wh * ww;
    let mut ql = Vec::with_capacity(k * k * lw);
    let mut kl = Vec::with_capacity(k * k * m * lw);
    for wy in 0..k {
        for wx in 0..k {
            let label = |p: usize| labels[(wy * wh + p / ww) * w + wx * ww + p % ww] as u8;
            ql.extend((0..lw).map(label));
            for v in 0..m {
                kl.extend((0..lw).map(|pos| label((pos * m + v) % lw)));
            }
        }
    }
    (ql, kl)
}

/// Additive mask for shifted-window attention with `m` key views per query: `[K·K, Lw, m·Lw]`, keys ordered
/// view-major (key `j = view·Lw + pos`).
///
/// The official multi-view code lays keys out position-major (`pos·m + view`) but tiles the single-view mask
/// with `repeat(b, 1, m)`, so key `(pos, view)` receives the mask column `(pos·m + view) mod Lw`, not `pos`.
/// We reproduce that exactly (the trained weights saw it); for `m = 1` it is the usual Swin mask.
pub fn shifted_window_mask(h: usize, w: usize, k: usize, m: usize, device: &Device) -> Result<Tensor> {
    let (wh, ww) = (h / k, w / k);
    let (sh, sw) = (wh / 2, ww / 2);
    let labels = region_labels(h, w, wh, ww, sh, sw);
    let lw = wh * ww;
    let mut out = vec![0f32; k * k * lw * m * lw];
    for wy in 0..k {
        for wx in 0..k {
            let win = wy * k + wx;
            let label = |p: usize| labels[(wy * wh + p / ww) * w + wx * ww + p % ww];
            for q in 0..lw {
                let lq = label(q);
                let row = &mut out[(win * lw + q) * m * lw..(win * lw + q + 1) * m * lw];
                for v in 0..m {
                    for pos in 0..lw {
                        let col = (pos * m + v) % lw;
                        row[v * lw + pos] = if label(col) != lq { -100.0 } else { 0.0 };
                    }
                }
            }
        }
    }
    Tensor::from_vec(out, (k * k, lw, m * lw), device)
}
