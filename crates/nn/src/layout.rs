//! Layout changes candle does single-threaded: a blocked, multi-threaded channels-last transpose on CPU f32
//! (inference); tracked inputs and other devices use candle's permute + copy.

use candle_core::{Result, Tensor};
use rayon::prelude::*;

/// `[B, V, C, H, W]` → `[B, V, H, W, C]` contiguous. Inference on CPU f32 uses a multi-threaded blocked
/// transpose (candle's strided copy is single-threaded; this tensor is ~275 MB at the DL3DV bench size).
pub fn channels_last(x: &Tensor) -> Result<Tensor> {
    let (b, v, c, h, w) = x.dims5()?;
    if x.track_op() || !crate::mode::cpu_f32(x) {
        return x.permute((0, 1, 3, 4, 2))?.contiguous();
    }
    let x = x.contiguous()?;
    let p = h * w;
    let mut out = vec![0f32; x.elem_count()];
    {
        let (st, l) = x.storage_and_layout();
        let src = match (&*st, l.contiguous_offsets()) {
            (candle_core::Storage::Cpu(candle_core::CpuStorage::F32(d)), Some((a, e))) => &d[a..e],
            _ => candle_core::bail!("channels_last: expected a contiguous CPU f32 tensor"),
        };
        const TILE: usize = 256;
        out.par_chunks_mut(c * p).zip(src.par_chunks(c * p)).for_each(|(dimg, simg)| {
            dimg.par_chunks_mut(TILE * c).enumerate().for_each(|(t, dst)| {
                let p0 = t * TILE;
                let np = dst.len() / c;
                for ci in 0..c {
                    for (j, &val) in simg[ci * p + p0..ci * p + p0 + np].iter().enumerate() {
                        dst[j * c + ci] = val;
                    }
                }
            });
        });
    }
    Tensor::from_vec(out, (b, v, h, w, c), x.device())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Values must be exact: it only moves them.
    #[test]
    fn channels_last_equals_permute() {
        let x = Tensor::randn(0f32, 1.0, (2, 3, 5, 17, 19), &candle_core::Device::Cpu).unwrap();
        let a = channels_last(&x).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let b = x.permute((0, 1, 3, 4, 2)).unwrap().contiguous().unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(a, b);
    }
}
