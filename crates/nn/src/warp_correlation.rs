//! Fused plane-sweep correlation: `out[n,d,p] = Σ_c ref[n,c,p] · grid_sample(src, grid)[n,c,d·h+y,x]` for a
//! fixed (gradient-free) sampling grid `[N, D·h, w, 2]`. Equals `(ref.unsqueeze(2) * warped).sum(1)` of the
//! official cost volume without materialising the `[N, C, D, h, w]` warped features (gigabytes at DL3DV size).
//! Backward w.r.t. both feature maps; the grid is a constant, as under the official `torch.no_grad()`. Other
//! devices run that composition itself (grid_sample, product, channel sum).

use std::sync::Arc;

use candle_core::{CpuStorage, CustomOp2, DType, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use crate::grid_sample::{taps_at, unnormalize, Taps};

#[derive(Clone)]
struct WarpCorrelation {
    /// `[N·D·P]` taps into the `h×w` source plane.
    taps: Arc<Vec<Taps>>,
    d: usize,
}

/// `[N, C, P]` → `[N, P, C]` (channels contiguous for the gathers).
fn to_nhwc(x: &[f32], n: usize, c: usize, p: usize) -> Vec<f32> {
    let mut out = vec![0f32; n * p * c];
    out.par_chunks_mut((p * c).max(1)).enumerate().for_each(|(ni, o)| {
        let xs = &x[ni * c * p..(ni + 1) * c * p];
        for ci in 0..c {
            for pi in 0..p {
                o[pi * c + ci] = xs[ci * p + pi];
            }
        }
    });
    out
}

fn from_nhwc(x: &[f32], n: usize, c: usize, p: usize) -> Vec<f32> {
    let mut out = vec![0f32; n * c * p];
    out.par_chunks_mut((c * p).max(1)).enumerate().for_each(|(ni, o)| {
        let xs = &x[ni * p * c..(ni + 1) * p * c];
        for pi in 0..p {
            for ci in 0..c {
                o[ci * p + pi] = xs[pi * c + ci];
            }
        }
    });
    out
}

/// Bilinear sample of one C-vector (the official order: interpolate each channel, then dot).
#[inline]
fn sample_into(buf: &mut [f32], src: &[f32], t: &Taps, c: usize) {
    let rows = [&src[t.idx[0] as usize * c..][..c], &src[t.idx[1] as usize * c..][..c], &src[t.idx[2] as usize * c..][..c], &src[t.idx[3] as usize * c..][..c]];
    for (ci, b) in buf.iter_mut().enumerate() {
        *b = t.w[0] * rows[0][ci] + t.w[1] * rows[1][ci] + t.w[2] * rows[2][ci] + t.w[3] * rows[3][ci];
    }
}

fn slice<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> Result<&'a [f32]> {
    crate::mode::f32_slice(s, l, &format!("warp_correlation {what}"))
}

impl CustomOp2 for WarpCorrelation {
    fn name(&self) -> &'static str {
        "warp_correlation"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> Result<(CpuStorage, Shape)> {
        let (n, c, h, w) = l1.shape().dims4()?;
        let p = h * w;
        let d = self.d;
        let r = to_nhwc(slice(s1, l1, "reference features")?, n, c, p);
        let s = to_nhwc(slice(s2, l2, "source features")?, n, c, p);
        let mut out = vec![0f32; n * d * p];
        out.par_chunks_mut(p.max(1)).enumerate().for_each(|(nd, o)| {
            let ni = nd / d.max(1);
            let src = &s[ni * p * c..(ni + 1) * p * c];
            let rf = &r[ni * p * c..(ni + 1) * p * c];
            let taps = &self.taps[nd * p..(nd + 1) * p];
            let mut buf = vec![0f32; c];
            for (pi, (y, t)) in o.iter_mut().zip(taps).enumerate() {
                sample_into(&mut buf, src, t, c);
                *y = buf.iter().zip(&rf[pi * c..(pi + 1) * c]).map(|(a, b)| a * b).sum();
            }
        });
        Ok((CpuStorage::F32(out), Shape::from((n, d, h, w))))
    }

    fn bwd(&self, reference: &Tensor, source: &Tensor, _res: &Tensor, grad_res: &Tensor) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (n, c, h, w) = reference.dims4()?;
        let p = h * w;
        let d = self.d;
        let flat = |t: &Tensor| -> Result<Vec<f32>> { t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>() };
        let r = to_nhwc(&flat(reference)?, n, c, p);
        let s = to_nhwc(&flat(source)?, n, c, p);
        let go = flat(grad_res)?;
        // d/d ref[n,p,:] = Σ_d go[n,d,p] · sampled(n,d,p)
        let mut gr = vec![0f32; n * p * c];
        gr.par_chunks_mut(c.max(1)).enumerate().for_each(|(np, g)| {
            let (ni, pi) = (np / p.max(1), np % p.max(1));
            let src = &s[ni * p * c..(ni + 1) * p * c];
            let mut buf = vec![0f32; c];
            for di in 0..d {
                let gv = go[(ni * d + di) * p + pi];
                if gv == 0.0 {
                    continue;
                }
                sample_into(&mut buf, src, &self.taps[(ni * d + di) * p + pi], c);
                for (a, b) in g.iter_mut().zip(&buf) {
                    *a += gv * b;
                }
            }
        });
        // d/d src[n,q,:] = Σ over taps hitting q of go·w·ref[n,p,:]; each image scatters into its own slab.
        let mut gs = vec![0f32; n * p * c];
        gs.par_chunks_mut((p * c).max(1)).enumerate().for_each(|(ni, g)| {
            let rf = &r[ni * p * c..(ni + 1) * p * c];
            for di in 0..d {
                for pi in 0..p {
                    let gv = go[(ni * d + di) * p + pi];
                    if gv == 0.0 {
                        continue;
                    }
                    let t = &self.taps[(ni * d + di) * p + pi];
                    let rv = &rf[pi * c..(pi + 1) * c];
                    for k in 0..4 {
                        let wk = t.w[k] * gv;
                        if wk != 0.0 {
                            let dst = &mut g[t.idx[k] as usize * c..(t.idx[k] as usize + 1) * c];
                            for (a, b) in dst.iter_mut().zip(rv) {
                                *a += wk * b;
                            }
                        }
                    }
                }
            }
        });
        let dev = reference.device();
        Ok((
            Some(Tensor::from_vec(from_nhwc(&gr, n, c, p), (n, c, h, w), dev)?.to_dtype(reference.dtype())?),
            Some(Tensor::from_vec(from_nhwc(&gs, n, c, p), (n, c, h, w), dev)?.to_dtype(source.dtype())?),
        ))
    }
}

/// `Σ_c reference[n,c,y,x] · grid_sample(source, grid)[n,c,d·h+y,x]` → `[N, D, h, w]`, with `grid` given flat as
/// `[N, D·h, w, 2]` (bilinear, zeros, align_corners=True; constant, no gradient). Differentiable w.r.t. both
/// feature maps `[N, C, h, w]`.
pub fn warp_correlation(reference: &Tensor, source: &Tensor, grid: &[f32], num_candidates: usize) -> Result<Tensor> {
    let (n, _, h, w) = reference.dims4()?;
    if source.dims() != reference.dims() {
        candle_core::bail!("warp_correlation: reference {:?} and source {:?} differ", reference.dims(), source.dims());
    }
    let d = num_candidates;
    let p = h * w;
    if grid.len() != n * d * p * 2 {
        candle_core::bail!("warp_correlation: grid has {} values, expected N·D·h·w·2 = {}", grid.len(), n * d * p * 2);
    }
    if !(crate::mode::cpu_f32(reference) && crate::mode::cpu_f32(source)) {
        return warp_correlation_composed(reference, source, grid, d);
    }
    let taps = grid_taps(grid, n * d, h, w);
    reference.contiguous()?.apply_op2(&source.contiguous()?, WarpCorrelation { taps: Arc::new(taps), d })
}

/// The bilinear taps of every grid point (`rows` rows of h·w points).
fn grid_taps(grid: &[f32], rows: usize, h: usize, w: usize) -> Vec<Taps> {
    let p = h * w;
    let mut taps = vec![Taps::default(); rows * p];
    taps.par_chunks_mut(p.max(1)).enumerate().for_each(|(nd, row)| {
        let g = &grid[nd * p * 2..(nd + 1) * p * 2];
        for (i, t) in row.iter_mut().enumerate() {
            *t = taps_at(unnormalize(g[2 * i], w), unnormalize(g[2 * i + 1], h), h, w);
        }
    });
    taps
}

/// [`warp_correlation`] as the official composition: warp all `D` candidates, multiply, sum over channels
/// (materialises `[N, C, D, h, w]`).
pub(crate) fn warp_correlation_composed(reference: &Tensor, source: &Tensor, grid: &[f32], d: usize) -> Result<Tensor> {
    let (n, c, h, w) = reference.dims4()?;
    let g = Tensor::from_slice(grid, (n, d * h, w, 2), reference.device())?.to_dtype(source.dtype())?;
    let warped = crate::grid_sample::grid_sample_composed(source, &g)?.reshape((n, c, d, h, w))?;
    warped.broadcast_mul(&reference.unsqueeze(2)?)?.sum(1)
}

/// [`warp_correlation`] with the channel dot products in bf16 (issue 73; inference, the encoder's
/// `--encoder-dtype bf16`): both feature maps rounded once to bf16 (nearest even) as channel pairs, and each output
/// `Σ_k w_k·(Σ_c ref_c·src_kc)` over the 4 bilinear taps — the dot products on `vdpbf16ps` with f32 sums, the
/// tap weights f32. The same value as the official "interpolate, then dot" in exact arithmetic; the order differs
/// only by roundings. Error model (u = 2⁻⁸), with A = Σ_k |w_k|·Σ_c |ref_c·src_kc|:
/// |got − exact| ≤ (2u + u² + (C + 8)·2⁻²⁴)·A + 8C·2⁻¹²⁶ (the flush of denormal operands and products).
/// Where this thread's [`crate::bf16::path`] is not `Dpbf16`, off the CPU, or with gradients: [`warp_correlation`].
pub fn warp_correlation_bf16(reference: &Tensor, source: &Tensor, grid: &[f32], num_candidates: usize) -> Result<Tensor> {
    let fast = [reference, source].iter().all(|t| crate::mode::cpu_f32(t) && !t.track_op()) && crate::bf16::path() == crate::bf16::Bf16Path::Dpbf16;
    if !fast || source.dims() != reference.dims() {
        return warp_correlation(reference, source, grid, num_candidates);
    }
    let (n, _, h, w) = reference.dims4()?;
    let d = num_candidates;
    if grid.len() != n * d * h * w * 2 {
        candle_core::bail!("warp_correlation: grid has {} values, expected N·D·h·w·2 = {}", grid.len(), n * d * h * w * 2);
    }
    let taps = grid_taps(grid, n * d, h, w);
    reference.contiguous()?.apply_op2_no_bwd(&source.contiguous()?, &WarpCorrelationBf16 { taps, d })
}

struct WarpCorrelationBf16 {
    taps: Vec<Taps>,
    d: usize,
}

impl CustomOp2 for WarpCorrelationBf16 {
    fn name(&self) -> &'static str {
        "warp_correlation_bf16"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> Result<(CpuStorage, Shape)> {
        let (n, c, h, w) = l1.shape().dims4()?;
        let (r, s) = (slice(s1, l1, "reference features")?, slice(s2, l2, "source features")?);
        let out = correlation_bf16::<false>(r, s, &self.taps, n, c, h * w, self.d)
            .ok_or_else(|| candle_core::Error::Msg("warp_correlation_bf16: no AVX512-BF16 on this thread".into()))?;
        Ok((CpuStorage::F32(out), Shape::from((n, self.d, h, w))))
    }
}

/// Words of bf16 channel pairs per pixel: C rounded up to whole zmm (32 channels), zero-padded.
fn pair_words(c: usize) -> usize {
    c.div_ceil(32) * 16
}

/// `[N, C, P]` → `[N, P, pair_words(C)]` words `bf16(x[2i]) | bf16(x[2i + 1]) << 16`, RNE (or truncated: the
/// tests' mutation), zero-padded past C.
fn to_pair_pixels<const TRUNC: bool>(x: &[f32], n: usize, c: usize, p: usize) -> Vec<u32> {
    let cw = pair_words(c);
    let nhwc = to_nhwc(x, n, c, p);
    let mut out = vec![0u32; n * p * cw];
    out.par_chunks_mut(cw * p.max(1)).zip(nhwc.par_chunks(c * p.max(1))).for_each(|(o, xs)| {
        for (pi, dst) in o.chunks_exact_mut(cw).enumerate() {
            let px = &xs[pi * c..(pi + 1) * c];
            for (i, wd) in dst[..c.div_ceil(2)].iter_mut().enumerate() {
                let (lo, hi) = (px[2 * i], if 2 * i + 1 < c { px[2 * i + 1] } else { 0.0 });
                let b = |v: f32| if TRUNC { v.to_bits() >> 16 } else { crate::bf16::f32_to_bf16(v) as u32 };
                *wd = b(lo) | b(hi) << 16;
            }
        }
    });
    out
}

/// The bf16 correlation on slices (`reference`, `source` `[N, C, P]`, taps `[N·D·P]`) → `[N, D, P]`; None
/// unless AVX512-BF16 runs on this thread.
#[allow(clippy::too_many_arguments)]
fn correlation_bf16<const TRUNC: bool>(reference: &[f32], source: &[f32], taps: &[Taps], n: usize, c: usize, p: usize, d: usize) -> Option<Vec<f32>> {
    assert!(reference.len() == n * c * p && source.len() == n * c * p && taps.len() == n * d * p, "warp_correlation_bf16: shapes");
    if crate::bf16::path() != crate::bf16::Bf16Path::Dpbf16 {
        return None;
    }
    let mut out = vec![0f32; n * d * p];
    #[cfg(target_arch = "x86_64")]
    {
        let cw = pair_words(c);
        let (r, s) = (to_pair_pixels::<TRUNC>(reference, n, c, p), to_pair_pixels::<TRUNC>(source, n, c, p));
        out.par_chunks_mut(p.max(1)).enumerate().for_each(|(nd, o)| {
            let ni = nd / d.max(1);
            let (rf, src) = (&r[ni * p * cw..(ni + 1) * p * cw], &s[ni * p * cw..(ni + 1) * p * cw]);
            // SAFETY: the path answered Dpbf16 (AVX-512F and AVX512-BF16); every tap index is < P (taps_at) and
            // both maps hold P rows of cw words.
            unsafe { avx::correlate_row(o, rf, src, &taps[nd * p..(nd + 1) * p], cw) };
        });
    }
    Some(out)
}

#[cfg(target_arch = "x86_64")]
mod avx {
    use std::arch::x86_64::*;

    use crate::grid_sample::Taps;

    #[inline]
    #[target_feature(enable = "avx512f,avx512bf16")]
    unsafe fn words(p: *const u32) -> __m512bh {
        std::mem::transmute::<__m512i, __m512bh>(_mm512_loadu_si512(p as *const _))
    }

    /// `o[i] = Σ_k w_k·(rf[i] · src[idx_k])` per pixel i, rows of `cw` pair words.
    #[target_feature(enable = "avx512f,avx512bf16")]
    pub(super) unsafe fn correlate_row(o: &mut [f32], rf: &[u32], src: &[u32], taps: &[Taps], cw: usize) {
        debug_assert!(rf.len() >= o.len() * cw && taps.len() >= o.len() && cw.is_multiple_of(16));
        let (r, s) = (rf.as_ptr(), src.as_ptr());
        for (i, (y, t)) in o.iter_mut().zip(taps).enumerate() {
            let mut acc = [_mm512_setzero_ps(); 4];
            let rows = t.idx.map(|j| s.add(j as usize * cw));
            for z in (0..cw).step_by(16) {
                let a = words(r.add(i * cw + z));
                for k in 0..4 {
                    acc[k] = _mm512_dpbf16_ps(acc[k], a, words(rows[k].add(z)));
                }
            }
            let mut v = _mm512_mul_ps(acc[0], _mm512_set1_ps(t.w[0]));
            for k in 1..4 {
                v = _mm512_fmadd_ps(acc[k], _mm512_set1_ps(t.w[k]), v);
            }
            *y = _mm512_reduce_add_ps(v);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bf16::{bf16_to_f32_daz, error_bound, f32_to_bf16, with_bf16_masked};
    use candle_core::Device;

    /// 2⁻²⁴, f32's unit roundoff.
    const ULP: f64 = 1.0 / 16_777_216.0;

    fn data(len: usize, lo: f32, hi: f32, seed: u64) -> Vec<f32> {
        let mut x = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        (0..len)
            .map(|_| {
                x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                lo + (hi - lo) * ((x >> 40) as f32 / (1u64 << 24) as f32)
            })
            .collect()
    }

    /// Per output: the f64 correlation Σ_k w_k Σ_c ref_c src_kc on the same taps (the operands as given, or
    /// rounded to bf16 as the kernel rounds them), and A = Σ_k |w_k| Σ_c |ref_c src_kc|.
    fn reference(r: &[f32], s: &[f32], taps: &[Taps], n: usize, c: usize, p: usize, d: usize, rounded: bool) -> (Vec<f64>, Vec<f64>) {
        let x = |v: f32| if rounded { bf16_to_f32_daz(f32_to_bf16(v)) as f64 } else { v as f64 };
        let (mut o, mut a) = (vec![0f64; n * d * p], vec![0f64; n * d * p]);
        for ni in 0..n {
            for di in 0..d {
                for pi in 0..p {
                    let i = (ni * d + di) * p + pi;
                    let t = &taps[i];
                    for k in 0..4 {
                        let q = t.idx[k] as usize;
                        let (dot, abs) = (0..c).fold((0f64, 0f64), |(dd, aa), ci| {
                            let v = x(r[(ni * c + ci) * p + pi]) * x(s[(ni * c + ci) * p + q]);
                            (dd + v, aa + v.abs())
                        });
                        o[i] += t.w[k] as f64 * dot;
                        a[i] += (t.w[k] as f64).abs() * abs;
                    }
                }
            }
        }
        (o, a)
    }

    struct Case {
        r: Vec<f32>,
        s: Vec<f32>,
        grid: Vec<f32>,
        n: usize,
        c: usize,
        h: usize,
        w: usize,
        d: usize,
    }

    fn case(n: usize, c: usize, h: usize, w: usize, d: usize, seed: u64) -> Case {
        let len = n * c * h * w;
        // The grid reaches past the borders (zero padding: taps with weight 0).
        Case { r: data(len, -1.0, 1.0, seed), s: data(len, -1.5, 1.5, seed + 1), grid: data(n * d * h * w * 2, -1.15, 1.15, seed + 2), n, c, h, w, d }
    }

    fn tensors(k: &Case) -> (Tensor, Tensor) {
        let t = |v: &[f32]| Tensor::from_slice(v, (k.n, k.c, k.h, k.w), &Device::Cpu).unwrap();
        (t(&k.r), t(&k.s))
    }

    /// Ok: the largest |got − o| / bound over outputs; Err names the first output past it. `rounded`: the
    /// tight check (only f32 sums and the flush may differ), else the module's model.
    fn check(got: &[f32], k: &Case, rounded: bool) -> std::result::Result<f64, String> {
        let p = k.h * k.w;
        let taps = grid_taps(&k.grid, k.n * k.d, k.h, k.w);
        let (o, a) = reference(&k.r, &k.s, &taps, k.n, k.c, p, k.d, rounded);
        let mut worst = 0f64;
        for (i, g) in got.iter().enumerate() {
            let flush = 8.0 * k.c as f64 * 2f64.powi(-126);
            let b = if rounded { (k.c as f64 + 8.0) * ULP * a[i] + flush } else { error_bound(k.c + 8, a[i]) + flush };
            let e = (*g as f64 - o[i]).abs();
            if e.is_nan() || e > b {
                return Err(format!("output {i}: {g} against {}, |err| {e:.3e} > {b:.3e}", o[i]));
            }
            worst = worst.max(e / b);
        }
        Ok(worst)
    }

    /// Against the f64 correlation of the f32 operands (the model) and of the rounded ones (tight), and against
    /// the f32 kernel within the model plus the f32 kernel's own (5C + 8)·2⁻²⁴·A: C = 128 (the encoder's), 64,
    /// and 37 / 5 (odd, a pair and a zmm padded), ragged maps, borders, two seeds.
    #[test]
    fn bf16_correlation_holds_the_error_model() {
        if crate::bf16::path() != crate::bf16::Bf16Path::Dpbf16 {
            eprintln!("no AVX512-BF16 on this CPU: warp_correlation_bf16 is warp_correlation there (see the masked test)");
            return;
        }
        let mut worst = [0f64; 2];
        for seed in [1u64, 2] {
            for (n, c, h, w, d) in [(2, 128, 5, 7, 3), (1, 64, 8, 3, 4), (2, 37, 4, 6, 2), (1, 5, 3, 3, 5)] {
                let k = case(n, c, h, w, d, seed * 10 + c as u64);
                let (r, s) = tensors(&k);
                let got = warp_correlation_bf16(&r, &s, &k.grid, d).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
                for (i, rounded) in [false, true].into_iter().enumerate() {
                    let wst = check(&got, &k, rounded).unwrap_or_else(|e| panic!("seed {seed} n {n} c {c} {h}x{w} d {d} (rounded {rounded}): {e}"));
                    worst[i] = worst[i].max(wst);
                }
                let f32s = warp_correlation(&r, &s, &k.grid, d).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
                let taps = grid_taps(&k.grid, n * d, h, w);
                let (_, a) = reference(&k.r, &k.s, &taps, n, c, h * w, d, false);
                for (i, (g, f)) in got.iter().zip(&f32s).enumerate() {
                    let b = error_bound(c + 8, a[i]) + (5.0 * c as f64 + 8.0) * ULP * a[i] + 8.0 * c as f64 * 2f64.powi(-126);
                    assert!(((*g - *f) as f64).abs() <= b, "seed {seed} c {c}: output {i} {g} against f32 {f} (bound {b:.3e})");
                }
            }
        }
        eprintln!("largest |err| / bound: model {:.3}, rounded operands {:.3}", worst[0], worst[1]);
        assert!(worst[0] > 0.0 && worst[1] > 0.0, "no rounding error at all is suspicious");
    }

    /// Truncated operands (what a truncating packer computes) fail: all values 1 + 2⁻⁷ − 2⁻²³ (RNE moves them
    /// by 2⁻²³, truncation by ≈ 2u) at the map's centre fail the model, and there a result 1 % off fails too;
    /// random operands truncated fail the tight check.
    #[test]
    fn truncation_and_a_moved_result_are_caught() {
        if crate::bf16::path() != crate::bf16::Bf16Path::Dpbf16 {
            return;
        }
        let run = |k: &Case, trunc: bool| {
            let taps = grid_taps(&k.grid, k.n * k.d, k.h, k.w);
            let p = k.h * k.w;
            if trunc {
                correlation_bf16::<true>(&k.r, &k.s, &taps, k.n, k.c, p, k.d).unwrap()
            } else {
                correlation_bf16::<false>(&k.r, &k.s, &taps, k.n, k.c, p, k.d).unwrap()
            }
        };
        let mut k = case(1, 64, 4, 5, 2, 3);
        let near = 1.0 + 2f32.powi(-7) - 2f32.powi(-23);
        k.r.iter_mut().chain(k.s.iter_mut()).for_each(|v| *v = near);
        k.grid.iter_mut().for_each(|g| *g = 0.0); // the map's centre: taps of weight 1 or ½
        check(&run(&k, false), &k, false).expect("RNE holds the model");
        check(&run(&k, true), &k, false).expect_err("truncation fails the model");
        // All terms positive (A = |o|): 1 % is past the model's ≈ 2u.
        let moved: Vec<f32> = run(&k, false).iter().map(|v| v * 1.01).collect();
        check(&moved, &k, false).expect_err("1 % off fails");
        let k = case(2, 128, 5, 7, 3, 4);
        check(&run(&k, false), &k, true).expect("RNE holds the tight check");
        check(&run(&k, true), &k, true).expect_err("truncation fails the tight check");
    }

    /// Masked (`bf16::with_bf16_masked`) the bf16 entry is `warp_correlation`, bit for bit; unmasked it is not.
    #[test]
    fn masked_equals_warp_correlation() {
        let k = case(2, 128, 5, 7, 3, 5);
        let (r, s) = tensors(&k);
        let v = |t: Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let f32s = v(warp_correlation(&r, &s, &k.grid, k.d).unwrap());
        let masked = with_bf16_masked(|| v(warp_correlation_bf16(&r, &s, &k.grid, k.d).unwrap()));
        assert!(masked.iter().zip(&f32s).all(|(a, b)| a.to_bits() == b.to_bits()), "masked: bit for bit");
        let plain = v(warp_correlation_bf16(&r, &s, &k.grid, k.d).unwrap());
        assert_eq!(plain != f32s, crate::bf16::path() == crate::bf16::Bf16Path::Dpbf16);
    }
}
