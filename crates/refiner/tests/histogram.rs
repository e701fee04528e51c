//! `match_histograms` against (1) small examples worked out by hand from the skimage definition and
//! (2) a deliberately naive reference written here: for every source pixel, its quantile is the fraction of
//! source pixels ≤ it; the reference curve is (fraction of reference pixels ≤ t, t) over the distinct reference
//! values t; the output is the piecewise-linear interpolation of that curve, clamped to its end values
//! (np.interp). O(n²) counting, no sorting or deduplication, so it shares no code path with the library.

use candle_core::{Device, Tensor};
use mvsplat360_refiner::histogram::{match_histograms, match_histograms_u8, HistogramError};

#[test]
fn hand_computed_single_channel_example() {
    // source values 0.1, 0.2 (×2), 0.9 → quantiles 1/4, 3/4, 1; reference 0, 1 → curve (1/2 → 0), (1 → 1).
    // 1/4 is left of the curve → 0; 3/4 is halfway → 0.5; 1 → 1.
    let img = Tensor::new(&[[[0.1f32, 0.2], [0.2, 0.9]]], &Device::Cpu).unwrap();
    let reference = Tensor::new(&[[[0.0f32, 1.0, 1.0, 0.0, 0.0, 1.0]]], &Device::Cpu).unwrap();
    let out = match_histograms(&img, &reference).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
    // reference 0,1,1,0,0,1: three of each → curve (1/2 → 0), (1 → 1): same answer.
    assert_eq!(out, vec![0.0, 0.5, 0.5, 1.0]);
}

#[test]
fn hand_computed_u8_example_truncates() {
    // Two channels interleaved. Channel 0: source 10, 20, 20, 90 vs reference 0, 255, 0, 255 → 0, 127.5, 127.5,
    // 255 → stored into uint8: 0, 127, 127, 255. Channel 1: constant source 7 (quantile 1) → largest reference 200.
    let img = [10u8, 7, 20, 7, 20, 7, 90, 7];
    let reference = [0u8, 3, 255, 200, 0, 3, 255, 100];
    let out = match_histograms_u8(&img, &reference, 2).unwrap();
    assert_eq!(out, vec![0, 200, 127, 200, 127, 200, 255, 200]);
}

/// The naive reference described in the file comment, for one channel.
fn naive(source: &[f32], reference: &[f32]) -> Vec<f32> {
    let n = source.len() as f64;
    let m = reference.len() as f64;
    let mut ts: Vec<f32> = Vec::new();
    for &t in reference {
        if !ts.contains(&t) {
            ts.push(t);
        }
    }
    ts.sort_by(|a, b| a.partial_cmp(b).unwrap());
    let curve: Vec<(f64, f64)> = ts.iter().map(|&t| (reference.iter().filter(|&&r| r <= t).count() as f64 / m, t as f64)).collect();
    source
        .iter()
        .map(|&s| {
            let q = source.iter().filter(|&&x| x <= s).count() as f64 / n;
            if q <= curve[0].0 {
                return curve[0].1 as f32;
            }
            for w in curve.windows(2) {
                let ((q0, v0), (q1, v1)) = (w[0], w[1]);
                if q <= q1 {
                    return (v0 + (v1 - v0) * (q - q0) / (q1 - q0)) as f32;
                }
            }
            curve[curve.len() - 1].1 as f32
        })
        .collect()
}

/// Deterministic values with many ties (multiples of 1/16) and a per-channel offset.
fn quantised(len: usize, seed: u32, offset: f32) -> Vec<f32> {
    let mut s = seed;
    (0..len)
        .map(|_| {
            s = s.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            ((s >> 8) % 17) as f32 / 16.0 * 0.8 + offset
        })
        .collect()
}

#[test]
fn three_channel_batch_matches_naive_reference() {
    let (n, c, h, w) = (2, 3, 9, 7);
    let (rh, rw) = (6, 11);
    let mut img = Vec::new();
    let mut reference = Vec::new();
    for k in 0..n * c {
        img.extend(quantised(h * w, 17 + k as u32, 0.05 * k as f32));
        // continuous-ish reference values (few ties) on a different grid size
        reference.extend(quantised(rh * rw, 91 + k as u32, 0.0).iter().enumerate().map(|(i, v)| v * v + 0.001 * i as f32 + 0.1 * k as f32));
    }
    let it = Tensor::from_vec(img.clone(), (n, c, h, w), &Device::Cpu).unwrap();
    let rt = Tensor::from_vec(reference.clone(), (n, c, rh, rw), &Device::Cpu).unwrap();
    let out = match_histograms(&it, &rt).unwrap();
    assert_eq!(out.dims(), &[n, c, h, w]);
    let out = out.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let mut max = 0f32;
    for k in 0..n * c {
        let expected = naive(&img[k * h * w..(k + 1) * h * w], &reference[k * rh * rw..(k + 1) * rh * rw]);
        for (a, e) in out[k * h * w..(k + 1) * h * w].iter().zip(&expected) {
            max = max.max((a - e).abs());
        }
    }
    assert!(max <= 1e-6, "max abs diff to the naive reference {max:.3e}");

    // Matching an image to itself is the identity.
    let same = match_histograms(&it, &it).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
    assert_eq!(same, img);
}

#[test]
fn channel_mismatch_and_nan_are_errors() {
    let a = Tensor::zeros((3, 2, 2), candle_core::DType::F32, &Device::Cpu).unwrap();
    let b = Tensor::zeros((1, 2, 2), candle_core::DType::F32, &Device::Cpu).unwrap();
    assert!(matches!(match_histograms(&a, &b), Err(HistogramError::Shape(_))));
    let nan = Tensor::new(&[[[f32::NAN, 0.0]]], &Device::Cpu).unwrap();
    let ok = Tensor::new(&[[[0.0f32, 1.0]]], &Device::Cpu).unwrap();
    assert!(matches!(match_histograms(&nan, &ok), Err(HistogramError::NaN { .. })));
}
