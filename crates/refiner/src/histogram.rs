//! Colour-histogram matching of refined frames to the 3DGS renders, with the semantics of
//! `skimage.exposure.match_histograms(image, reference, channel_axis=-1)` (MVSplat360 `post_process.py`):
//! per channel, each distinct source value's cumulative quantile is mapped through `np.interp` onto the
//! reference's (quantile → value) curve.

use candle_core::{DType, Tensor};

#[derive(Debug, thiserror::Error)]
pub enum HistogramError {
    #[error("histogram matching: {0}")]
    Shape(String),
    #[error("histogram matching: {what} contains NaN; match only finite images")]
    NaN { what: &'static str },
    #[error("histogram matching: {0}")]
    Tensor(#[from] candle_core::Error),
}

/// Distinct values (ascending) with their counts, and for every input element the index of its value
/// (`np.unique(..., return_inverse=True, return_counts=True)`; −0.0 and 0.0 are one value, as in numpy).
fn unique_counts(v: &[f32], what: &'static str) -> Result<(Vec<f32>, Vec<u64>, Vec<u32>), HistogramError> {
    if v.iter().any(|x| x.is_nan()) {
        return Err(HistogramError::NaN { what });
    }
    let key = |x: f32| if x == 0.0 { 0.0 } else { x };
    let mut order: Vec<u32> = (0..v.len() as u32).collect();
    order.sort_unstable_by(|&a, &b| key(v[a as usize]).total_cmp(&key(v[b as usize])));
    let mut values = Vec::new();
    let mut counts = Vec::new();
    let mut inverse = vec![0u32; v.len()];
    for &i in &order {
        let x = key(v[i as usize]);
        if values.last() != Some(&x) {
            values.push(x);
            counts.push(0);
        }
        let last = counts.len() - 1;
        counts[last] += 1;
        inverse[i as usize] = last as u32;
    }
    Ok((values, counts, inverse))
}

/// `np.cumsum(counts) / size` in f64.
fn quantiles(counts: &[u64]) -> Vec<f64> {
    let size: u64 = counts.iter().sum();
    let mut acc = 0u64;
    counts
        .iter()
        .map(|&c| {
            acc += c;
            acc as f64 / size as f64
        })
        .collect()
}

/// `np.interp(x, xp, fp)` for one point; xp strictly increasing and non-empty.
fn interp(x: f64, xp: &[f64], fp: &[f64]) -> f64 {
    let last = xp.len() - 1;
    if x <= xp[0] {
        // numpy returns fp[0] left of the range (and at xp[0]).
        return fp[0];
    }
    if x >= xp[last] {
        return fp[last];
    }
    // largest j with xp[j] <= x (< last here)
    let j = xp.partition_point(|&v| v <= x) - 1;
    if x == xp[j] {
        return fp[j];
    }
    let slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j]);
    slope * (x - xp[j]) + fp[j]
}

/// skimage `_match_cumulative_cdf` for float data: returns f64 values (skimage casts them to the image dtype).
pub fn match_cumulative_cdf(source: &[f32], template: &[f32]) -> Result<Vec<f64>, HistogramError> {
    if source.is_empty() || template.is_empty() {
        return Err(HistogramError::Shape("empty image or reference".into()));
    }
    let (_, src_counts, src_inverse) = unique_counts(source, "image")?;
    let (tmpl_values, tmpl_counts, _) = unique_counts(template, "reference")?;
    let src_q = quantiles(&src_counts);
    let tmpl_q = quantiles(&tmpl_counts);
    let fp: Vec<f64> = tmpl_values.iter().map(|&v| v as f64).collect();
    let mapped: Vec<f64> = src_q.iter().map(|&q| interp(q, &tmpl_q, &fp)).collect();
    Ok(src_inverse.iter().map(|&i| mapped[i as usize]).collect())
}

/// `match_histograms(image, reference, channel_axis=-1)` on f32 images in our (C, H, W) layout
/// (or a batch (N, C, H, W), each image matched to its own reference). Spatial sizes may differ; channel
/// counts must agree. Output f32 (skimage keeps float32 for float32 input).
pub fn match_histograms(image: &Tensor, reference: &Tensor) -> Result<Tensor, HistogramError> {
    let (id, rd) = (image.dims(), reference.dims());
    let (n, c) = match (id.len(), rd.len()) {
        (3, 3) => (1, id[0]),
        (4, 4) if id[0] == rd[0] => (id[0], id[1]),
        _ => return Err(HistogramError::Shape(format!("image {id:?} and reference {rd:?} must both be (C,H,W) or (N,C,H,W) with equal N"))),
    };
    if rd[rd.len() - 3] != c {
        return Err(HistogramError::Shape(format!("number of channels differs: image {id:?}, reference {rd:?}")));
    }
    let src = image.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    let tmpl = reference.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    let (ps, pt) = (src.len() / (n * c), tmpl.len() / (n * c));
    let mut out = Vec::with_capacity(src.len());
    for k in 0..n * c {
        let m = match_cumulative_cdf(&src[k * ps..(k + 1) * ps], &tmpl[k * pt..(k + 1) * pt])?;
        out.extend(m.into_iter().map(|v| v as f32));
    }
    Ok(Tensor::from_vec(out, id, image.device())?)
}

/// The official post-processing exactly: `match_histograms` on uint8 images read from PNG, interleaved
/// (H, W, C) with `channels` channels. skimage's uint8 path (bincount) maps through the same quantiles and
/// stores the float result into a uint8 array, i.e. truncates.
pub fn match_histograms_u8(image: &[u8], reference: &[u8], channels: usize) -> Result<Vec<u8>, HistogramError> {
    if channels == 0 || image.len() % channels != 0 || reference.len() % channels != 0 || image.is_empty() || reference.is_empty() {
        return Err(HistogramError::Shape(format!("{} / {} values are not non-empty (H, W, {channels}) images", image.len(), reference.len())));
    }
    let mut out = vec![0u8; image.len()];
    for ch in 0..channels {
        let mut src_counts = [0u64; 256];
        let mut tmpl_counts = [0u64; 256];
        image.iter().skip(ch).step_by(channels).for_each(|&v| src_counts[v as usize] += 1);
        reference.iter().skip(ch).step_by(channels).for_each(|&v| tmpl_counts[v as usize] += 1);
        let src_q = quantiles(&src_counts);
        let present: Vec<usize> = (0..256).filter(|&v| tmpl_counts[v] > 0).collect();
        let tmpl_q = quantiles(&present.iter().map(|&v| tmpl_counts[v]).collect::<Vec<_>>());
        let fp: Vec<f64> = present.iter().map(|&v| v as f64).collect();
        let lut: Vec<u8> = src_q.iter().map(|&q| interp(q, &tmpl_q, &fp) as u8).collect();
        for (o, &v) in out.iter_mut().zip(image.iter()).skip(ch).step_by(channels) {
            *o = lut[v as usize];
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn interp_follows_numpy_edges() {
        let xp = [0.5, 1.0];
        let fp = [0.0, 1.0];
        assert_eq!(interp(0.25, &xp, &fp), 0.0);
        assert_eq!(interp(0.5, &xp, &fp), 0.0);
        assert_eq!(interp(0.75, &xp, &fp), 0.5);
        assert_eq!(interp(1.0, &xp, &fp), 1.0);
        assert_eq!(interp(2.0, &xp, &fp), 1.0);
    }

    #[test]
    fn unique_merges_signed_zero_and_counts() {
        let (v, c, inv) = unique_counts(&[0.5, -0.0, 0.0, 0.5, -1.0], "image").unwrap();
        assert_eq!(v, vec![-1.0, 0.0, 0.5]);
        assert_eq!(c, vec![1, 2, 2]);
        assert_eq!(inv, vec![2, 1, 1, 2, 0]);
    }
}
