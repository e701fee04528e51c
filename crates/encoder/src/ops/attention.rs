//! Fused inference attention on the CPU: `softmax(q·kᵀ + mask)·v` per batch item, computed in row blocks so the
//! score matrix only ever lives in a small per-task buffer (never the whole `[B, Lq, S]` tensor). No backward:
//! callers use it only when no input tracks gradients and keep the composed ops for training.

use candle_core::{CpuStorage, CustomOp3, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use crate::backbone::nn::exp_fast;

/// Swin region labels: score `(b, i, j)` gets −100 added where `q_labels[b mod P][i] != k_labels[b mod P][j]`
/// (equal to adding the dense shifted-window mask, without materialising it).
#[derive(Debug, Clone)]
pub struct RegionMask {
    /// `[P, Lq]`
    pub q_labels: Vec<u8>,
    /// `[P, S]`
    pub k_labels: Vec<u8>,
    pub p: usize,
}

struct FusedAttention<'a> {
    mask: Option<&'a RegionMask>,
}

/// Score-buffer budget per task (floats). Each block re-packs k and v inside gemm, so blocks need ≳ 100 query
/// rows to amortise that (measured on the DL3DV bench: 27-row blocks 6.4 s of transformer, 146-row blocks 5.4 s).
const BLOCK_FLOATS: usize = 512 * 1024;

fn slice<'a>(s: &'a CpuStorage, l: &Layout) -> Result<&'a [f32]> {
    match (s, l.contiguous_offsets()) {
        (CpuStorage::F32(v), Some((a, b))) => Ok(&v[a..b]),
        _ => candle_core::bail!("fused attention: needs contiguous f32 inputs"),
    }
}

#[derive(Clone, Copy)]
struct SendPtr(*mut f32);
unsafe impl Send for SendPtr {}
unsafe impl Sync for SendPtr {}

impl CustomOp3 for FusedAttention<'_> {
    fn name(&self) -> &'static str {
        "fused-attention"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout, s3: &CpuStorage, l3: &Layout) -> Result<(CpuStorage, Shape)> {
        let (q, k, v) = (slice(s1, l1)?, slice(s2, l2)?, slice(s3, l3)?);
        let (b, lq, c) = l1.shape().dims3()?;
        let (_, s, _) = l2.shape().dims3()?;
        let cv = l3.shape().dims3()?.2;
        if let Some(m) = self.mask {
            if m.p == 0 || b % m.p != 0 || m.q_labels.len() != m.p * lq || m.k_labels.len() != m.p * s {
                candle_core::bail!("fused attention: region mask does not fit the scores");
            }
        }
        let rows = (BLOCK_FLOATS / s.max(1)).clamp(8, 256).min(lq.max(1));
        let blocks = lq.div_ceil(rows);
        let mut out = vec![0f32; b * lq * cv];
        let optr = SendPtr(out.as_mut_ptr());
        (0..b * blocks).into_par_iter().for_each_init(
            || vec![0f32; rows * s],
            |buf, task| {
                let optr = optr;
                let (bi, blk) = (task / blocks, task % blocks);
                let r0 = blk * rows;
                let nr = rows.min(lq - r0);
                let qb = &q[(bi * lq + r0) * c..];
                let kb = &k[bi * s * c..];
                let vb = &v[bi * s * cv..];
                // SAFETY: buf is nr × s (row stride s); q rows r0.. of item bi (nr × c); kᵀ read as c × s with
                // column stride c; v is s × cv; the output rows (bi, r0..r0+nr) belong to this task only.
                unsafe {
                    gemm::gemm(
                        nr, s, c,
                        buf.as_mut_ptr(), 1, s as isize, false,
                        qb.as_ptr(), 1, c as isize,
                        kb.as_ptr(), c as isize, 1,
                        0.0, 1.0, false, false, false, gemm::Parallelism::None,
                    );
                }
                let labels = self.mask.map(|m| {
                    let pi = bi % m.p;
                    (&m.q_labels[pi * lq + r0..][..nr], &m.k_labels[pi * s..][..s])
                });
                softmax_rows(&mut buf[..nr * s], s, labels);
                unsafe {
                    gemm::gemm(
                        nr, cv, s,
                        optr.0.add((bi * lq + r0) * cv), 1, cv as isize, false,
                        buf.as_ptr(), 1, s as isize,
                        vb.as_ptr(), 1, cv as isize,
                        0.0, 1.0, false, false, false, gemm::Parallelism::None,
                    );
                }
            },
        );
        Ok((CpuStorage::F32(out), Shape::from((b, lq, cv))))
    }
}

/// Masked softmax of each row (length `s`) of `buf` in place.
#[inline(always)]
fn softmax_rows_impl(buf: &mut [f32], s: usize, labels: Option<(&[u8], &[u8])>) {
    for (r, row) in buf.chunks_exact_mut(s).enumerate() {
        if let Some((ql, kl)) = labels {
            let lab = ql[r];
            row.iter_mut().zip(kl).for_each(|(x, &l)| *x += if l != lab { -100.0 } else { 0.0 });
        }
        let mx = row.iter().fold(f32::NEG_INFINITY, |a, &x| a.max(x));
        let mut acc = [0f32; 8];
        let mut chunks = row.chunks_exact_mut(8);
        for ch in &mut chunks {
            for i in 0..8 {
                ch[i] = exp_fast(ch[i] - mx);
                acc[i] += ch[i];
            }
        }
        let mut sum: f32 = acc.iter().sum();
        for x in chunks.into_remainder() {
            *x = exp_fast(*x - mx);
            sum += *x;
        }
        let inv = 1.0 / sum;
        row.iter_mut().for_each(|x| *x *= inv);
    }
}

/// The same code compiled for AVX2 (the default x86-64 target only vectorises 4 lanes); no FMA, so the results
/// are bit-identical to the portable path.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn softmax_rows_avx2(buf: &mut [f32], s: usize, labels: Option<(&[u8], &[u8])>) {
    softmax_rows_impl(buf, s, labels)
}

fn softmax_rows(buf: &mut [f32], s: usize, labels: Option<(&[u8], &[u8])>) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 is available on this CPU.
        return unsafe { softmax_rows_avx2(buf, s, labels) };
    }
    softmax_rows_impl(buf, s, labels)
}

/// Whether [`fused_attention`] can run: CPU f32 and no input tracks gradients.
pub fn fused_attention_applies(ts: &[&Tensor]) -> bool {
    ts.iter().all(|t| t.device().is_cpu() && t.dtype() == candle_core::DType::F32 && !t.track_op())
}

/// `q [B, Lq, C]`, `k [B, S, C]`, `v [B, S, Cv]` → `softmax(q·kᵀ (+ region mask))·v`, `[B, Lq, Cv]`
/// (q carries any scale). Inference only: the result has no backward.
pub fn fused_attention(q: &Tensor, k: &Tensor, v: &Tensor, mask: Option<&RegionMask>) -> Result<Tensor> {
    let (b, _, c) = q.dims3()?;
    let (bk, s, ck) = k.dims3()?;
    let (bv, sv, _) = v.dims3()?;
    if bk != b || bv != b || ck != c || sv != s {
        candle_core::bail!("fused attention: shapes q {:?}, k {:?}, v {:?} do not match", q.dims(), k.dims(), v.dims());
    }
    q.contiguous()?.apply_op3_no_bwd(&k.contiguous()?, &v.contiguous()?, &FusedAttention { mask })
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, D};

    /// Fused attention (with and without region mask) equals the composed definition to 1e-5.
    #[test]
    fn fused_attention_matches_composed() -> Result<()> {
        let dev = Device::Cpu;
        let (b, lq, s, c, cv, p) = (4, 37, 53, 16, 12, 2);
        let q = Tensor::randn(0f32, 1.0, (b, lq, c), &dev)?;
        let k = Tensor::randn(0f32, 1.0, (b, s, c), &dev)?;
        let v = Tensor::randn(0f32, 1.0, (b, s, cv), &dev)?;
        let q_labels: Vec<u8> = (0..p * lq).map(|i| ((i * 7) % 3) as u8).collect();
        let k_labels: Vec<u8> = (0..p * s).map(|i| ((i * 5) % 3) as u8).collect();
        let mut dense = vec![0f32; p * lq * s];
        for pi in 0..p {
            for i in 0..lq {
                for j in 0..s {
                    if q_labels[pi * lq + i] != k_labels[pi * s + j] {
                        dense[(pi * lq + i) * s + j] = -100.0;
                    }
                }
            }
        }
        let dense = Tensor::from_vec(dense, (1, p, lq, s), &dev)?;
        let mask = RegionMask { q_labels, k_labels, p };
        for m in [None, Some(&mask)] {
            let got = fused_attention(&q, &k, &v, m)?;
            let mut sc = q.matmul(&k.t()?)?;
            if m.is_some() {
                sc = sc.reshape((b / p, p, lq, s))?.broadcast_add(&dense)?.reshape((b, lq, s))?;
            }
            let e = sc.broadcast_sub(&sc.max_keepdim(D::Minus1)?)?.exp()?;
            let want = e.broadcast_div(&e.sum_keepdim(D::Minus1)?)?.matmul(&v)?;
            let d = (got - want)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            assert!(d < 1e-5, "fused attention diff {d}");
        }
        Ok(())
    }
}
