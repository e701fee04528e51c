//! The DPT heads' positional embedding (`heads/utils.py`): a UV grid spanning the image's aspect ratio,
//! normalised by its diagonal, embedded with sines and cosines (base 100).

/// PyTorch's float32 `linspace` (the first half counts up from `start`, the second down from `end`).
fn linspace_f32(start: f32, end: f32, steps: usize) -> Vec<f32> {
    if steps == 1 {
        return vec![start];
    }
    let step = (end - start) / (steps - 1) as f32;
    let half = steps / 2;
    (0..steps).map(|i| if i < half { start + step * i as f32 } else { end - step * (steps - 1 - i) as f32 }).collect()
}

/// The axes of `create_uv_grid(width, height, aspect_ratio)` in float32: u per column, v per row.
pub fn uv_axes(width: usize, height: usize, aspect_ratio: f64) -> (Vec<f32>, Vec<f32>) {
    let diag = (aspect_ratio * aspect_ratio + 1.0).sqrt();
    let span_x = aspect_ratio / diag;
    let span_y = 1.0 / diag;
    let lx = -span_x * (width as f64 - 1.0) / width as f64;
    let ty = -span_y * (height as f64 - 1.0) / height as f64;
    (linspace_f32(lx as f32, -lx as f32, width), linspace_f32(ty as f32, -ty as f32, height))
}

/// `create_uv_grid(width, height, aspect_ratio)`: `(height, width)` pairs `(u, v)`, row-major.
pub fn create_uv_grid(width: usize, height: usize, aspect_ratio: f64) -> Vec<(f32, f32)> {
    let (xs, ys) = uv_axes(width, height, aspect_ratio);
    ys.iter().flat_map(|&y| xs.iter().map(move |&x| (x, y))).collect()
}

/// `position_grid_to_embed(create_uv_grid(width, height, aspect), dim)` · `ratio`, channels-first
/// `(dim, height·width)`: channels `[sin(u·ω), cos(u·ω), sin(v·ω), cos(v·ω)]`, ω_k = 100^(−k/(dim/4)),
/// products and functions in f64 as upstream (its frequencies are float64), rounded to f32, then scaled by
/// `ratio` in f32. u depends on the column only and v on the row, so each value is computed once per column or
/// row and repeated (at the image size: 52 k evaluations instead of 19.5 M, the same numbers).
pub fn position_embed_uv(width: usize, height: usize, aspect_ratio: f64, dim: usize, ratio: f32) -> Vec<f32> {
    let (xs, ys) = uv_axes(width, height, aspect_ratio);
    let q = dim / 4;
    let omega: Vec<f64> = (0..q).map(|k| 1.0 / 100f64.powf(k as f64 / q as f64)).collect();
    let n = width * height;
    let mut out = vec![0f32; dim * n];
    for (part, axis) in [&xs, &ys].into_iter().enumerate() {
        for (k, w) in omega.iter().enumerate() {
            let sin: Vec<f32> = axis.iter().map(|&p| ((p as f64 * w).sin() as f32) * ratio).collect();
            let cos: Vec<f32> = axis.iter().map(|&p| ((p as f64 * w).cos() as f32) * ratio).collect();
            for (ch, vals) in [(part * 2 * q + k, &sin), (part * 2 * q + q + k, &cos)] {
                let plane = &mut out[ch * n..(ch + 1) * n];
                for (y, row) in plane.chunks_exact_mut(width).enumerate() {
                    if part == 0 {
                        row.copy_from_slice(vals);
                    } else {
                        row.fill(vals[y]);
                    }
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uv_grid_is_centred_and_diagonal_normalised() {
        // 4 × 2 grid, aspect 2: span_x = 2/√5, span_y = 1/√5; corners at ±span·(n−1)/n.
        let g = create_uv_grid(4, 2, 2.0);
        let sx = 2.0 / 5f64.sqrt() * 0.75;
        let sy = 1.0 / 5f64.sqrt() * 0.5;
        assert!((g[0].0 as f64 + sx).abs() < 1e-6 && (g[0].1 as f64 + sy).abs() < 1e-6);
        assert!((g[7].0 as f64 - sx).abs() < 1e-6 && (g[7].1 as f64 - sy).abs() < 1e-6);
        assert_eq!(g.len(), 8);
    }

    /// The separable embedding equals upstream's per-point formula (`position_grid_to_embed` on the grid)
    /// bit for bit, on odd and even sizes and aspects.
    #[test]
    fn separable_embedding_equals_the_per_point_formula() {
        for (w, h, dim) in [(37, 21, 64), (4, 2, 8), (19, 11, 1024), (1, 3, 4)] {
            let aspect = (w * 14) as f64 / (h * 14) as f64;
            let grid = create_uv_grid(w, h, aspect);
            let q = dim / 4;
            let omega: Vec<f64> = (0..q).map(|k| 1.0 / 100f64.powf(k as f64 / q as f64)).collect();
            let n = grid.len();
            let mut want = vec![0f32; dim * n];
            for (i, &(u, v)) in grid.iter().enumerate() {
                for (part, p) in [u, v].into_iter().enumerate() {
                    for (k, om) in omega.iter().enumerate() {
                        let a = p as f64 * om;
                        want[(part * 2 * q + k) * n + i] = (a.sin() as f32) * 0.1;
                        want[(part * 2 * q + q + k) * n + i] = (a.cos() as f32) * 0.1;
                    }
                }
            }
            let got = position_embed_uv(w, h, aspect, dim, 0.1);
            assert!(got.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()), "{w}x{h} dim {dim}");
        }
    }
}
