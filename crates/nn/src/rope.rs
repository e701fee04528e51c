//! Self-attention from a packed `qkv` projection with per-head LayerNorm on q and k (QK-norm) and 2D rotary
//! position embedding (VGGT's aggregator). On CPU f32 the norms and rotations run in place on one copy of the
//! projection, and the attention kernel reads q, k and v where they lie (column offsets), so no head split,
//! transpose or concatenation is materialised.

use candle_core::{Result, Tensor, D};
use rayon::prelude::*;

use crate::attention::{attention_raw, exp_sub_sum, for_each_row_block, row_max, AttnOperand, OnlineRows, RowBlock, SeqLayout};
use crate::math::{exp_f32, simd_dispatch};
use crate::mode::{is_cpu_f32, with_f32};
use crate::{attention64, attention64_bf16};

/// LayerNorm over one head's features.
#[derive(Clone, Copy)]
pub struct HeadNorm<'a> {
    pub weight: &'a Tensor,
    pub bias: &'a Tensor,
    pub eps: f64,
}

/// Rotation tables of a sequence, `(L, d)` each: feature j of token l becomes
/// `x[j]·cos[l, j] + rot(x)[j]·sin[l, j]`, where `rot` works on each half of the head (the first half rotates
/// with the token's y, the second with its x) as `(x1, x2) → (−x2, x1)` on that half's two quarters.
#[derive(Clone, Copy)]
pub struct Rope2dTables<'a> {
    pub cos: &'a Tensor,
    pub sin: &'a Tensor,
}

/// `(cos, sin)` tables `(L, d)` for positions `(y, x)` per token, base frequency `base`: within each half of
/// the head (size `d/2`), quarter-pair i ∈ [0, d/4) turns by `p · base^(−4i/d)`, duplicated over the half's
/// two quarters. Angles are formed in f32 as PyTorch forms them (`arange(0, F, 2).float() / F`, `1/base^e`,
/// positions × frequencies) before the cosine and sine.
pub fn rope2d_tables(positions: &[(u32, u32)], d: usize, base: f64) -> (Vec<f32>, Vec<f32>) {
    let half = d / 2;
    let quarter = half / 2;
    let inv_freq: Vec<f32> = (0..quarter).map(|i| 1.0f32 / (base as f32).powf((2 * i) as f32 / half as f32)).collect();
    let mut cos = vec![0f32; positions.len() * d];
    let mut sin = vec![0f32; positions.len() * d];
    for (l, &(y, x)) in positions.iter().enumerate() {
        for (h, p) in [y, x].into_iter().enumerate() {
            for (i, f) in inv_freq.iter().enumerate() {
                let a = p as f32 * f;
                let (s, c) = (a.sin(), a.cos());
                for j in [h * half + i, h * half + quarter + i] {
                    cos[l * d + j] = c;
                    sin[l * d + j] = s;
                }
            }
        }
    }
    (cos, sin)
}

/// `qkv (N, L, 3·H·d)` (PyTorch's `qkv(x).reshape(B, N, 3, H, d)` order) → scaled dot-product attention
/// `(N, L, H·d)`, with q and k each normalised per head, then rotated, when given.
pub fn qkv_attention(qkv: &Tensor, heads: usize, q_norm: Option<HeadNorm>, k_norm: Option<HeadNorm>, rope: Option<Rope2dTables>) -> Result<Tensor> {
    qkv_attention_with(qkv, heads, q_norm, k_norm, rope, false)
}

/// [`qkv_attention`] with both products in bf16 where the fused kernel for heads of 64 runs (x86-64 with
/// AVX-512F and AVX512-BF16, [`crate::bf16::path`] on the calling thread): q, k, v and the softmax's
/// exponentials rounded to bf16, f32 accumulation and softmax (error model in `attention64_bf16`). Elsewhere —
/// other head sizes, no AVX512-BF16, masked by [`crate::bf16::with_bf16_masked`], other devices or dtypes —
/// exactly [`qkv_attention`] (no weights here, so bf16 storage has nothing to hold).
pub fn qkv_attention_bf16(qkv: &Tensor, heads: usize, q_norm: Option<HeadNorm>, k_norm: Option<HeadNorm>, rope: Option<Rope2dTables>) -> Result<Tensor> {
    qkv_attention_with(qkv, heads, q_norm, k_norm, rope, true)
}

fn qkv_attention_with(
    qkv: &Tensor,
    heads: usize,
    q_norm: Option<HeadNorm>,
    k_norm: Option<HeadNorm>,
    rope: Option<Rope2dTables>,
    bf16: bool,
) -> Result<Tensor> {
    let (n, l, three_c) = qkv.dims3()?;
    if heads == 0 || three_c % (3 * heads) != 0 {
        candle_core::bail!("qkv attention: width {three_c} is not 3 × {heads} heads");
    }
    let c = three_c / 3;
    let d = c / heads;
    if let Some(r) = rope {
        if r.cos.dims() != [l, d] || r.sin.dims() != [l, d] || !d.is_multiple_of(4) {
            candle_core::bail!("qkv attention: rope tables {:?} for {l} tokens of head size {d}", r.cos.dims());
        }
    }
    if !is_cpu_f32(qkv) {
        return qkv_attention_composed(qkv, heads, q_norm, k_norm, rope);
    }
    let prepared = prepare(qkv, heads, q_norm, k_norm, rope)?;
    let mut out = vec![0f32; n * l * c];
    let run = |buf: &[f32], out: &mut [f32]| {
        if bf16 && d == attention64::D && attention64_bf16::attention_d64_bf16(buf, n, l, c, heads, out, attention64::Q_BLOCK, attention64::K_CHUNK) {
            // done: the fused kernel with bf16 products (AVX512-BF16)
        } else if d == attention64::D && attention64::attention_d64(buf, n, l, c, heads, out, attention64::Q_BLOCK, attention64::K_CHUNK) {
            // done: the fused kernel (AVX-512)
        } else if l <= K_CHUNK {
            let layout = SeqLayout::contiguous(n, l);
            attention_raw(
                AttnOperand { data: buf, row_len: three_c, col_offset: 0 },
                layout,
                AttnOperand { data: buf, row_len: three_c, col_offset: c },
                AttnOperand { data: buf, row_len: three_c, col_offset: 2 * c },
                layout,
                out,
                c,
                heads,
                d,
                1.0 / (d as f32).sqrt(),
            );
        } else {
            attention_chunked(buf, n, l, c, heads, d, out);
        }
    };
    match &prepared {
        Some(buf) => run(buf, &mut out),
        None => with_f32(qkv, |buf| run(buf, &mut out))?,
    }
    Tensor::from_vec(out, (n, l, c), qkv.device())
}

/// QK-norm and RoPE applied to a copy of the CPU f32 projection (one parallel pass, each row copied and its q
/// and k transformed); None without either, and the kernels read the tensor's own storage.
pub(crate) fn prepare(qkv: &Tensor, heads: usize, q_norm: Option<HeadNorm>, k_norm: Option<HeadNorm>, rope: Option<Rope2dTables>) -> Result<Option<Vec<f32>>> {
    let (n, l, three_c) = qkv.dims3()?;
    let c = three_c / 3;
    let d = c / heads;
    let vec1 = |t: &Tensor| t.to_dtype(candle_core::DType::F32)?.to_vec1::<f32>();
    let qn = q_norm.map(|h| Ok::<_, candle_core::Error>((vec1(h.weight)?, vec1(h.bias)?, h.eps))).transpose()?;
    let kn = k_norm.map(|h| Ok::<_, candle_core::Error>((vec1(h.weight)?, vec1(h.bias)?, h.eps))).transpose()?;
    let tables = rope.map(|r| Ok::<_, candle_core::Error>((r.cos.flatten_all()?.to_vec1::<f32>()?, r.sin.flatten_all()?.to_vec1::<f32>()?))).transpose()?;
    if qn.is_none() && kn.is_none() && tables.is_none() {
        return Ok(None);
    }
    let mut buf = vec![0f32; n * l * three_c];
    with_f32(qkv, |src| {
        buf.par_chunks_mut(three_c).zip(src.par_chunks(three_c)).enumerate().for_each(|(row, (r, s))| {
            r.copy_from_slice(s);
            let tok = row % l;
            for (part, norm) in [(0usize, &qn), (1, &kn)] {
                for h in 0..heads {
                    let x = &mut r[part * c + h * d..part * c + (h + 1) * d];
                    if let Some((w, b, eps)) = norm {
                        head_layer_norm(x, w, b, *eps);
                    }
                    if let Some((cos, sin)) = &tables {
                        rotate(x, &cos[tok * d..(tok + 1) * d], &sin[tok * d..(tok + 1) * d]);
                    }
                }
            }
        })
    })?;
    Ok(Some(buf))
}

/// Query rows per task and keys per chunk of [`attention_chunked`]: a 1024 × 256 score block (1 MiB, a core's L2
/// on Zen 4), each packed key/value chunk serving 1024 query rows. Measured on 2 Zen 4 cores for VGGT-1B's
/// global attention (3910 tokens, 16 heads of 64): 131 GFLOP/s, against 116 at 256 × 512, 98 at 128 × 512 and
/// 75 for the flash-style kernel of `attention` (67-row blocks over all keys).
const Q_BLOCK: usize = 1024;
const K_CHUNK: usize = 256;

/// Long sequences where `attention64`'s fused kernel does not run (heads other than 64, no AVX-512): per (sequence, head,
/// block of query rows), keys and values in chunks with an online softmax (running row max and sum; the
/// accumulated output is rescaled when the max grows), so the scores stay in L2 and each key chunk is packed
/// once per block of rows.
/// `buf`: rows of `[q | k | v]` (width 3c), `n` sequences of `l` rows.
fn attention_chunked(buf: &[f32], n: usize, l: usize, c: usize, heads: usize, d: usize, out: &mut [f32]) {
    attention_chunked_with(buf, n, l, c, heads, d, out, Q_BLOCK, K_CHUNK)
}

#[allow(clippy::too_many_arguments)]
fn attention_chunked_with(buf: &[f32], n: usize, l: usize, c: usize, heads: usize, d: usize, out: &mut [f32], q_block: usize, k_chunk: usize) {
    let row = 3 * c;
    let scale = 1.0 / (d as f32).sqrt();
    let qb = q_block.min(l).max(1);
    for_each_row_block(
        n,
        l,
        c,
        heads,
        d,
        q_block,
        out,
        || vec![0f32; qb * k_chunk],
        |b, st, s| {
            let RowBlock { g, h, q0, m } = b;
            let OnlineRows { acc, mx, sum } = st;
            let base = g * l;
            for j0 in (0..l).step_by(k_chunk) {
                let kc = k_chunk.min(l - j0);
                // SAFETY: q rows q0..q0+m, k/v rows j0..j0+kc of sequence g and head h's columns lie inside `buf`;
                // `s` holds m × kc and `acc` m × d floats.
                unsafe {
                    gemm::gemm(
                        m,
                        kc,
                        d,
                        s.as_mut_ptr(),
                        1,
                        kc as isize,
                        false,
                        buf.as_ptr().add((base + q0) * row + h * d),
                        1,
                        row as isize,
                        buf.as_ptr().add((base + j0) * row + c + h * d),
                        row as isize,
                        1,
                        0.0,
                        scale,
                        false,
                        false,
                        false,
                        gemm::Parallelism::None,
                    );
                }
                online_softmax_chunk(&mut s[..m * kc], kc, &mut mx[..m], &mut sum[..m], &mut acc[..m * d], d);
                unsafe {
                    gemm::gemm(
                        m,
                        d,
                        kc,
                        acc.as_mut_ptr(),
                        1,
                        d as isize,
                        true,
                        s.as_ptr(),
                        1,
                        kc as isize,
                        buf.as_ptr().add((base + j0) * row + 2 * c + h * d),
                        1,
                        row as isize,
                        1.0,
                        1.0,
                        false,
                        false,
                        false,
                        gemm::Parallelism::None,
                    );
                }
            }
        },
    );
}

simd_dispatch! {
    /// One key chunk of the online softmax: scores `s` (rows × kc) become exp(s − new row max) in place; each
    /// row's running sum and accumulated output are rescaled by exp(old max − new max).
    fn online_softmax_chunk(s: &mut [f32], kc: usize, mx: &mut [f32], sum: &mut [f32], acc: &mut [f32], d: usize) {
        for (r, row) in s.chunks_exact_mut(kc).enumerate() {
            let m_new = row_max(row).max(mx[r]);
            let corr = exp_f32(mx[r] - m_new);
            let rs = exp_sub_sum(row, m_new);
            sum[r] = sum[r] * corr + rs;
            if corr != 1.0 {
                for a in &mut acc[r * d..(r + 1) * d] {
                    *a *= corr;
                }
            }
            mx[r] = m_new;
        }
    }
}

/// PyTorch's LayerNorm statistics (biased variance), taken in f64.
fn head_layer_norm(x: &mut [f32], w: &[f32], b: &[f32], eps: f64) {
    let n = x.len() as f64;
    let mean = x.iter().map(|&v| v as f64).sum::<f64>() / n;
    let var = x.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / n;
    let inv = 1.0 / (var + eps).sqrt();
    for ((v, w), b) in x.iter_mut().zip(w).zip(b) {
        *v = ((*v as f64 - mean) * inv) as f32 * w + b;
    }
}

fn rotate(x: &mut [f32], cos: &[f32], sin: &[f32]) {
    let half = x.len() / 2;
    let q = half / 2;
    for h in 0..2 {
        let base = h * half;
        for i in 0..q {
            let (a, b) = (x[base + i], x[base + q + i]);
            x[base + i] = a * cos[base + i] - b * sin[base + i];
            x[base + q + i] = b * cos[base + q + i] + a * sin[base + q + i];
        }
    }
}

/// [`qkv_attention`] from tensor ops (any device, any float dtype).
fn qkv_attention_composed(qkv: &Tensor, heads: usize, q_norm: Option<HeadNorm>, k_norm: Option<HeadNorm>, rope: Option<Rope2dTables>) -> Result<Tensor> {
    let (n, l, three_c) = qkv.dims3()?;
    let c = three_c / 3;
    let d = c / heads;
    let prep = |part: usize, norm: Option<HeadNorm>| -> Result<Tensor> {
        let mut x = qkv.narrow(D::Minus1, part * c, c)?.reshape((n, l, heads, d))?;
        if let Some(h) = norm {
            x = crate::norm::layer_norm(&x, &h.weight.to_dtype(x.dtype())?, &h.bias.to_dtype(x.dtype())?, h.eps)?;
        }
        if let Some(r) = rope {
            let q4 = d / 4;
            let quarter = |i: usize| x.narrow(D::Minus1, i * q4, q4);
            let rot = Tensor::cat(&[&quarter(1)?.neg()?, &quarter(0)?, &quarter(3)?.neg()?, &quarter(2)?], D::Minus1)?;
            let cos = r.cos.to_dtype(x.dtype())?.reshape((1, l, 1, d))?;
            let sin = r.sin.to_dtype(x.dtype())?.reshape((1, l, 1, d))?;
            x = (x.broadcast_mul(&cos)? + rot.broadcast_mul(&sin)?)?;
        }
        x.reshape((n, l, c))
    };
    let q = prep(0, q_norm)?;
    let k = prep(1, k_norm)?;
    let v = qkv.narrow(D::Minus1, 2 * c, c)?.contiguous()?;
    crate::attention::multi_head_attention(&q.contiguous()?, &k.contiguous()?, &v, heads, 1 << 26)
}

/// Test data and the error check shared by the attention kernels' tests (here and in `attention64`).
#[cfg(test)]
pub(crate) mod test_support {
    use candle_core::{Device, Tensor};

    /// Deterministic `[q | k | v]` rows `(n, l, 3c)` from a fixed LCG, uniform in [−amp, amp).
    pub(crate) fn qkv_data(n: usize, l: usize, c: usize, amp: f32, seed: u64) -> Tensor {
        let mut x = seed;
        let v: Vec<f32> = (0..n * l * 3 * c)
            .map(|_| {
                x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((x >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0) * amp
            })
            .collect();
        Tensor::from_vec(v, (n, l, 3 * c), &Device::Cpu).unwrap()
    }

    /// `fast` within the worst-case f32 error of either side from `slow`, and that bound tight enough that
    /// `fast` × 1.01 fails it. In units of u·max|v|, per side: a score's dot product of d terms
    /// (≤ d·u·scale·max|q|·max|k| absolute, which moves the weights by as much relatively), the weighted sum over
    /// l keys (≤ l·u), the running rescale per chunk and the final division; twice (both sides round). The
    /// magnitudes come from `qkv` (q and k as the scores see them: after any QK-norm).
    pub(crate) fn assert_within_attention_bound(fast: &Tensor, slow: &Tensor, qkv: &Tensor, c: usize, d: usize, l: usize, what: &str) {
        let max_abs = |t: &Tensor| t.abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        let max_diff = |a: &Tensor, b: &Tensor| max_abs(&(a - b).unwrap());
        let (q, k, v) = (max_abs(&qkv.narrow(2, 0, c).unwrap()), max_abs(&qkv.narrow(2, c, c).unwrap()), max_abs(&qkv.narrow(2, 2 * c, c).unwrap()));
        let b = 2.0 * f32::EPSILON * v * (d as f32 * q * k / (d as f32).sqrt() + l as f32 + 8.0);
        let diff = max_diff(fast, slow);
        assert!(diff <= b, "{what}: max diff {diff} over {b}");
        assert!(max_diff(&(fast * 1.01).unwrap(), slow) > b, "{what}: the bound {b} is too loose to see a 1 % error");
    }
}

#[cfg(test)]
mod tests {
    use super::test_support::{assert_within_attention_bound, qkv_data};
    use super::*;
    use candle_core::Device;

    /// The CPU kernel against the composed ops (run in differentiable mode, which takes the composed path).
    #[test]
    fn kernel_matches_composed_ops() {
        let dev = Device::Cpu;
        let (n, l, heads, d) = (3, 11, 2, 8);
        let c = heads * d;
        let qkv = Tensor::randn(0f32, 1.0, (n, l, 3 * c), &dev).unwrap();
        let w = (Tensor::randn(0f32, 0.3, d, &dev).unwrap() + 1.0).unwrap();
        let b = Tensor::randn(0f32, 0.1, d, &dev).unwrap();
        let pos: Vec<(u32, u32)> = (0..l as u32).map(|i| (i / 4, i % 4 + 1)).collect();
        let (cos, sin) = rope2d_tables(&pos, d, 100.0);
        let cos = Tensor::from_vec(cos, (l, d), &dev).unwrap();
        let sin = Tensor::from_vec(sin, (l, d), &dev).unwrap();
        let norm = Some(HeadNorm { weight: &w, bias: &b, eps: 1e-5 });
        let rope = Some(Rope2dTables { cos: &cos, sin: &sin });
        let fast = qkv_attention(&qkv, heads, norm, norm, rope).unwrap();
        let slow = {
            let _g = crate::mode::differentiable();
            qkv_attention(&qkv, heads, norm, norm, rope).unwrap()
        };
        let diff = (fast - slow).unwrap().abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(diff < 1e-5, "max diff {diff}");
    }

    /// The chunked kernel (online softmax over key chunks) against the composed ops: through the public path
    /// just past the threshold, and with small blocks so that several query blocks and key chunks (ragged last
    /// ones included) run on small sizes.
    #[test]
    fn long_sequences_match_composed_ops() {
        let dev = Device::Cpu;
        let (heads, d) = (2, 8);
        let c = heads * d;
        let composed = |qkv: &Tensor| {
            let _g = crate::mode::differentiable();
            qkv_attention(qkv, heads, None, None, None).unwrap()
        };
        let check = |fast: &Tensor, qkv: &Tensor, l: usize, what: &str| assert_within_attention_bound(fast, &composed(qkv), qkv, c, d, l, what);
        let qkv = qkv_data(2, K_CHUNK + 1, c, 2.0, 1);
        check(&qkv_attention(&qkv, heads, None, None, None).unwrap(), &qkv, K_CHUNK + 1, "public path");
        for (i, (n, l, qb, kc)) in [(1, 100, 32, 16), (3, 77, 20, 30), (2, 64, 64, 64), (1, 5, 4, 2)].into_iter().enumerate() {
            let qkv = qkv_data(n, l, c, 3.0, 7 + i as u64);
            let buf = qkv.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let mut out = vec![0f32; n * l * c];
            attention_chunked_with(&buf, n, l, c, heads, d, &mut out, qb, kc);
            check(&Tensor::from_vec(out, (n, l, c), &dev).unwrap(), &qkv, l, &format!("n {n} l {l} blocks {qb}x{kc}"));
        }
    }

    /// Rotating by position p then taking dot products depends only on the offset (RoPE's defining property),
    /// per axis: checks the tables and the rotation together in closed form.
    #[test]
    fn rotation_is_relative() {
        let d = 8;
        let x: Vec<f32> = (0..d).map(|i| (i as f32 * 0.7).sin()).collect();
        let y: Vec<f32> = (0..d).map(|i| (i as f32 * 1.3).cos()).collect();
        let dot_at = |px: (u32, u32), py: (u32, u32)| {
            let (c, s) = rope2d_tables(&[px, py], d, 100.0);
            let (mut a, mut b) = (x.clone(), y.clone());
            rotate(&mut a, &c[..d], &s[..d]);
            rotate(&mut b, &c[d..], &s[d..]);
            a.iter().zip(&b).map(|(p, q)| p * q).sum::<f32>()
        };
        let base = dot_at((3, 5), (1, 2));
        let shifted = dot_at((7, 9), (5, 6));
        assert!((base - shifted).abs() < 1e-4, "{base} vs {shifted}");
        assert!((base - dot_at((3, 5), (2, 2))).abs() > 1e-3, "y offset must matter");
        assert!((base - dot_at((3, 5), (1, 3))).abs() > 1e-3, "x offset must matter");
    }
}
