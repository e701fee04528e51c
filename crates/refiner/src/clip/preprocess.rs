//! sgm `FrozenOpenCLIPImageEmbedder.preprocess`: kornia antialiased bicubic resize (ported as diffusers
//! `_resize_with_antialiasing`) to the CLIP input size, then CLIP mean/std normalisation.

use candle_core::{DType, Result, Tensor};
use rayon::prelude::*;

/// OpenAI CLIP normalisation constants (sgm registers them as buffers `mean`/`std`), digits as published.
#[allow(clippy::excessive_precision)]
pub const CLIP_MEAN: [f32; 3] = [0.481_454_66, 0.457_827_5, 0.408_210_73];
#[allow(clippy::excessive_precision)]
pub const CLIP_STD: [f32; 3] = [0.268_629_54, 0.261_302_58, 0.275_777_11];

/// Gaussian sigma and odd kernel size for one axis: σ = max((factor−1)/2, 0.001), k = int(max(4σ, 3)) made odd.
fn blur_params(input: usize, output: usize) -> (f32, usize) {
    let factor = input as f64 / output as f64;
    let sigma = ((factor - 1.0) / 2.0).max(0.001);
    let mut k = (4.0 * sigma).max(3.0) as usize;
    if k % 2 == 0 {
        k += 1;
    }
    (sigma as f32, k)
}

/// Normalised Gaussian taps in f32 (kornia / diffusers compute them in the input dtype).
fn gaussian(k: usize, sigma: f32) -> Vec<f32> {
    let half = (k / 2) as f32;
    let g: Vec<f32> = (0..k).map(|i| (-(i as f32 - half).powi(2) / (2.0 * sigma * sigma)).exp()).collect();
    let s: f32 = g.iter().sum();
    g.into_iter().map(|v| v / s).collect()
}

/// torch `reflect` padding index (edge not repeated).
fn reflect(i: isize, n: usize) -> usize {
    let n = n as isize;
    if n == 1 {
        return 0;
    }
    let period = 2 * (n - 1);
    let mut m = i.rem_euclid(period);
    if m >= n {
        m = period - m;
    }
    m as usize
}

/// 1-D blur of a (h, w) plane along x (`horizontal`) or y, reflect padding, odd kernel.
fn blur_axis(src: &[f32], h: usize, w: usize, taps: &[f32], horizontal: bool) -> Vec<f32> {
    let r = (taps.len() / 2) as isize;
    let mut out = vec![0f32; h * w];
    for y in 0..h {
        for x in 0..w {
            let mut acc = 0f32;
            for (t, &g) in taps.iter().enumerate() {
                let o = t as isize - r;
                let v = if horizontal { src[y * w + reflect(x as isize + o, w)] } else { src[reflect(y as isize + o, h) * w + x] };
                acc += g * v;
            }
            out[y * w + x] = acc;
        }
    }
    out
}

/// PyTorch bicubic convolution weights (A = −0.75) for fractional offset t.
fn cubic_weights(t: f32) -> [f32; 4] {
    const A: f32 = -0.75;
    let c1 = |x: f32| ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0;
    let c2 = |x: f32| ((A * x - 5.0 * A) * x + 8.0 * A) * x - 4.0 * A;
    [c2(t + 1.0), c1(t), c1(1.0 - t), c2(2.0 - t)]
}

/// Source taps (clamped indices, weights) for each output index, align_corners=True.
fn bicubic_taps(input: usize, output: usize) -> Vec<([usize; 4], [f32; 4])> {
    let scale = if output > 1 { (input as f32 - 1.0) / (output as f32 - 1.0) } else { 0.0 };
    (0..output)
        .map(|o| {
            let real = scale * o as f32;
            let i0 = real.floor();
            let t = real - i0;
            let i0 = i0 as isize;
            let idx = [-1isize, 0, 1, 2].map(|d| (i0 + d).clamp(0, input as isize - 1) as usize);
            (idx, cubic_weights(t))
        })
        .collect()
}

fn bicubic_plane(src: &[f32], h: usize, w: usize, oh: usize, ow: usize) -> Vec<f32> {
    let ty = bicubic_taps(h, oh);
    let tx = bicubic_taps(w, ow);
    let mut out = vec![0f32; oh * ow];
    for (oy, (iy, wy)) in ty.iter().enumerate() {
        for (ox, (ix, wx)) in tx.iter().enumerate() {
            let mut acc = 0f32;
            for a in 0..4 {
                let row = &src[iy[a] * w..];
                let r = wx[0] * row[ix[0]] + wx[1] * row[ix[1]] + wx[2] * row[ix[2]] + wx[3] * row[ix[3]];
                acc += wy[a] * r;
            }
            out[oy * ow + ox] = acc;
        }
    }
    out
}

/// diffusers `_resize_with_antialiasing` (kornia `resize(..., antialias=True)`, bicubic, align_corners=True)
/// of (N, C, H, W) to (N, C, oh, ow): Gaussian blur along x then y, then bicubic interpolation.
pub fn resize_with_antialiasing(x: &Tensor, oh: usize, ow: usize) -> Result<Tensor> {
    let (n, c, h, w) = x.dims4()?;
    let (sy, ky) = blur_params(h, oh);
    let (sx, kx) = blur_params(w, ow);
    if (ky / 2) >= h.max(2) || (kx / 2) >= w.max(2) {
        candle_core::bail!("antialiased resize: blur kernel {ky}x{kx} too large for a {h}x{w} image (reflect padding)");
    }
    let (gy, gx) = (gaussian(ky, sy), gaussian(kx, sx));
    let data = x.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    let mut out = vec![0f32; n * c * oh * ow];
    out.par_chunks_mut(oh * ow).zip(data.par_chunks(h * w)).for_each(|(dst, plane)| {
        let bx = blur_axis(plane, h, w, &gx, true);
        let b = blur_axis(&bx, h, w, &gy, false);
        dst.copy_from_slice(&bicubic_plane(&b, h, w, oh, ow));
    });
    Tensor::from_vec(out, (n, c, oh, ow), x.device())
}

/// Views (N, 3, H, W) in [0, 1] → CLIP pixel values (N, 3, size, size): x·2−1 (sgm conditioner input),
/// antialiased bicubic resize, (x+1)/2, CLIP mean/std.
pub fn clip_preprocess(views: &Tensor, size: usize) -> Result<Tensor> {
    let (_, c, _, _) = views.dims4()?;
    if c != 3 {
        candle_core::bail!("CLIP preprocessing expects 3-channel views, got {:?}", views.dims());
    }
    let x = views.to_dtype(DType::F32)?.affine(2.0, -1.0)?;
    let x = resize_with_antialiasing(&x, size, size)?.affine(0.5, 0.5)?;
    let dev = views.device();
    let mean = Tensor::new(&CLIP_MEAN, dev)?.reshape((1, 3, 1, 1))?;
    let std = Tensor::new(&CLIP_STD, dev)?.reshape((1, 3, 1, 1))?;
    x.broadcast_sub(&mean)?.broadcast_div(&std)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reflect_matches_torch() {
        let idx: Vec<usize> = (-3..8).map(|i| reflect(i, 5)).collect();
        assert_eq!(idx, vec![3, 2, 1, 0, 1, 2, 3, 4, 3, 2, 1]);
    }

    #[test]
    fn blur_params_follow_the_formula() {
        // 256 → 224: σ = 0.0714, k = 3; 448 → 224: σ = 0.5, k = int(2.0) = 2 → 3; 1024 → 224: σ = 1.786, k = 7.
        assert_eq!(blur_params(256, 224).1, 3);
        assert_eq!(blur_params(448, 224), (0.5, 3));
        assert_eq!(blur_params(1024, 224).1, 7);
        assert_eq!(blur_params(100, 224), (0.001, 3));
    }

    #[test]
    fn bicubic_reproduces_linear_ramps_inside_and_identity_at_same_size() {
        // Cubic convolution (any A, here −0.75) sums to one and reproduces linear functions away from borders.
        let w = 12;
        let src: Vec<f32> = (0..w).map(|i| 0.7 * i as f32 - 3.0).collect();
        let out = bicubic_plane(&src, 1, w, 1, 23);
        let scale = (w - 1) as f32 / 22.0;
        for (o, v) in out.iter().enumerate() {
            let x = o as f32 * scale;
            if x >= 1.0 && x <= (w - 2) as f32 {
                let exact = 0.7 * x - 3.0;
                assert!((v - exact).abs() < 1e-4, "x {x}: {v} vs {exact}");
            }
        }
        let same = bicubic_plane(&src, 1, w, 1, w);
        assert_eq!(same, src);
    }
}
