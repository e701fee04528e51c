//! `mvsplat360 bench bf16`: the `vdpbf16ps` / `vfmadd231ps` peak microbenchmark and the bf16 gemm against the
//! f32 gemm on the model's shapes. FLOP counting: an f32 FMA lane is 2 FLOP (16 lanes per zmm), a `vdpbf16ps`
//! lane is 2 multiply-adds = 4 FLOP (16 f32 lanes, 32 bf16 pairs per zmm); a gemm is 2·M·N·K FLOP. Peaks and
//! GFLOP/s are of the fastest run (the least disturbed on a shared machine); the gemm JSON has medians too.

use std::time::Instant;

use super::{matmul_bf16, path, Bf16Path, Bf16Weights};

/// Independent accumulators per thread in the microbenchmark (each a zmm register).
pub const ACCUMULATORS: usize = 12;

/// What to run.
pub struct Bf16BenchOpts {
    /// Worker threads for the "all cores" figures and the gemms.
    pub threads: usize,
    /// Timed repetitions (the median is reported).
    pub runs: usize,
    /// Gemm shapes (M, K, N); empty: only the microbenchmark.
    pub shapes: Vec<(usize, usize, usize)>,
    /// Inner-loop iterations of one microbenchmark run (each issues [`ACCUMULATORS`] instructions).
    pub micro_iters: u64,
}

impl Default for Bf16BenchOpts {
    fn default() -> Self {
        Bf16BenchOpts { threads: 1, runs: 5, shapes: default_shapes(), micro_iters: 40_000_000 }
    }
}

/// The shapes: VGGT-1B block linears over 5 frames of 518×294 (5·(777+5) = 3910 tokens): qkv/fc1
/// (1024 → 3072, 1024 → 4096), fc2 (4096 → 1024); the SVD UNet's first-level 3×3 convolution as a gemm
/// (64×112 latent pixels, K = 9·320, 320 outputs).
pub fn default_shapes() -> Vec<(usize, usize, usize)> {
    vec![(3910, 1024, 3072), (3910, 4096, 1024), (3910, 1024, 4096), (7168, 2880, 320)]
}

/// CPU name, family and model from /proc/cpuinfo.
pub fn cpu_model() -> (String, String, String) {
    let info = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let field = |key: &str| {
        info.lines()
            .find(|l| l.split(':').next().map(str::trim) == Some(key))
            .and_then(|l| l.split_once(':'))
            .map(|(_, v)| v.trim().to_string())
            .unwrap_or_else(|| "unknown".into())
    };
    (field("model name"), field("cpu family"), field("model"))
}

#[cfg(target_arch = "x86_64")]
mod micro {
    use std::arch::x86_64::*;

    /// `iters` × N independent `vfmadd231ps zmm`; returns a lane sum (kept live).
    #[target_feature(enable = "avx512f")]
    pub unsafe fn fma<const N: usize>(iters: u64) -> f32 {
        let x = _mm512_set1_ps(std::hint::black_box(1.0e-7));
        let y = _mm512_set1_ps(std::hint::black_box(1.0e-7));
        let mut acc = [_mm512_setzero_ps(); N];
        for (i, a) in acc.iter_mut().enumerate() {
            *a = _mm512_set1_ps(std::hint::black_box(i as f32));
        }
        for _ in 0..iters {
            for a in acc.iter_mut() {
                *a = _mm512_fmadd_ps(x, y, *a);
            }
            std::arch::asm!("", options(nomem, nostack, preserves_flags));
        }
        acc.iter().map(|a| _mm512_reduce_add_ps(*a)).sum()
    }

    /// `iters` × N independent `vdpbf16ps zmm`.
    #[target_feature(enable = "avx512f,avx512bf16")]
    pub unsafe fn dpbf16<const N: usize>(iters: u64) -> f32 {
        let x: __m512bh = _mm512_cvtne2ps_pbh(_mm512_set1_ps(std::hint::black_box(1.0e-7)), _mm512_set1_ps(1.0e-7));
        let y: __m512bh = _mm512_cvtne2ps_pbh(_mm512_set1_ps(std::hint::black_box(1.0e-7)), _mm512_set1_ps(1.0e-7));
        let mut acc = [_mm512_setzero_ps(); N];
        for (i, a) in acc.iter_mut().enumerate() {
            *a = _mm512_set1_ps(std::hint::black_box(i as f32));
        }
        for _ in 0..iters {
            for a in acc.iter_mut() {
                *a = _mm512_dpbf16_ps(*a, x, y);
            }
            std::arch::asm!("", options(nomem, nostack, preserves_flags));
        }
        acc.iter().map(|a| _mm512_reduce_add_ps(*a)).sum()
    }
}

/// One microbenchmark loop: `iters` iterations, a value kept live.
type Loop = fn(u64) -> f32;

/// GFLOP/s of `threads` threads each running `f(iters)` (wall time of all), the fastest of `runs`.
fn rate(threads: usize, runs: usize, iters: u64, flop_per_iter: f64, f: Loop) -> f64 {
    let once = || {
        let t = Instant::now();
        std::thread::scope(|s| {
            let hs: Vec<_> = (0..threads).map(|_| s.spawn(move || std::hint::black_box(f(iters)))).collect();
            for h in hs {
                let _ = h.join();
            }
        });
        t.elapsed().as_secs_f64()
    };
    once();
    let times: Vec<f64> = (0..runs.max(1)).map(|_| once()).collect();
    // The fastest run: a peak, least disturbed by other processes.
    let best = times.into_iter().fold(f64::INFINITY, f64::min);
    threads as f64 * iters as f64 * flop_per_iter / best / 1e9
}

/// A JSON number, `null` for NaN (not measured).
fn num(x: f64) -> String {
    if x.is_finite() {
        format!("{x:.3}")
    } else {
        "null".into()
    }
}

/// Deterministic values in [-1, 1) (xorshift).
pub(crate) fn fill(len: usize, seed: u64) -> Vec<f32> {
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..len)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        })
        .collect()
}

pub(crate) fn f32_gemm(a: &[f32], b: &[f32], c: &mut [f32], m: usize, k: usize, n: usize, threads: usize) {
    let par = if threads > 1 { gemm::Parallelism::Rayon(threads) } else { gemm::Parallelism::None };
    // SAFETY: a is m×k, b k×n, c m×n, all row-major and of those lengths.
    unsafe {
        gemm::gemm(m, n, k, c.as_mut_ptr(), 1, n as isize, false, a.as_ptr(), 1, k as isize, b.as_ptr(), 1, n as isize, 0.0, 1.0, false, false, false, par);
    }
}

/// Runs the benchmark and returns its JSON line.
pub fn run(opts: &Bf16BenchOpts) -> Result<String, String> {
    let (name, family, model) = cpu_model();
    let threads = opts.threads.max(1);
    let runs = opts.runs.max(1);
    let p = path();
    let mut out =
        format!("{{\"bench\":\"bf16\",\"cpu\":{:?},\"cpu_family\":{:?},\"cpu_model\":{:?},\"threads\":{threads},\"path\":{:?}", name, family, model, p.name());
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx512f") {
        let dp_ok = p == Bf16Path::Dpbf16;
        // (accumulators, fma, dpbf16) — SAFETY: avx512f was detected; dpbf16 runs only where `dp_ok`.
        let kernels: [(usize, Loop, Loop); 4] = [
            (4, |i| unsafe { micro::fma::<4>(i) }, |i| unsafe { micro::dpbf16::<4>(i) }),
            (8, |i| unsafe { micro::fma::<8>(i) }, |i| unsafe { micro::dpbf16::<8>(i) }),
            (12, |i| unsafe { micro::fma::<12>(i) }, |i| unsafe { micro::dpbf16::<12>(i) }),
            (16, |i| unsafe { micro::fma::<16>(i) }, |i| unsafe { micro::dpbf16::<16>(i) }),
        ];
        let mut sweep = Vec::new();
        let mut main = String::new();
        for (acc, fma, dp) in kernels {
            let fma_flop = (acc * 16 * 2) as f64;
            let dp_flop = (acc * 16 * 4) as f64;
            let iters = opts.micro_iters * ACCUMULATORS as u64 / acc as u64;
            let f1 = rate(1, runs, iters, fma_flop, fma);
            let d1 = if dp_ok { rate(1, runs, iters, dp_flop, dp) } else { f64::NAN };
            sweep.push(format!("{{\"accumulators\":{acc},\"fma_gflops_1\":{f1:.1},\"dpbf16_gflops_1\":{}}}", num(d1)));
            if acc == ACCUMULATORS {
                let fa = rate(threads, runs, iters, fma_flop, fma);
                let da = if dp_ok { rate(threads, runs, iters, dp_flop, dp) } else { f64::NAN };
                main = format!(
                    "\"accumulators\":{acc},\"fma_gflops_1\":{f1:.1},\"dpbf16_gflops_1\":{},\"ratio_1\":{},\"fma_gflops_all\":{fa:.1},\"dpbf16_gflops_all\":{},\"ratio_all\":{}",
                    num(d1),
                    num(d1 / f1),
                    num(da),
                    num(da / fa)
                );
            }
        }
        out += &format!(
            ",\"micro\":{{\"flop_count\":\"vfmadd231ps zmm: 16 lanes x 2 FLOP; vdpbf16ps zmm: 16 f32 lanes x 2 multiply-adds = 64 FLOP\",{main},\"sweep\":[{}]}}",
            sweep.join(",")
        );
    }
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().map_err(|e| e.to_string())?;
    let mut rows = Vec::new();
    for &(m, k, n) in &opts.shapes {
        let a = fill(m * k, 1);
        let b = fill(k * n, 2);
        let flop = 2.0 * (m * n * k) as f64;
        let row = pool.install(|| {
            let mut c32 = vec![0f32; m * n];
            let t = Instant::now();
            let w = Bf16Weights::from_kn(&b, k, n);
            let pack_ms = t.elapsed().as_secs_f64() * 1e3;
            let mut c16 = vec![0f32; m * n];
            f32_gemm(&a, &b, &mut c32, m, k, n, threads);
            matmul_bf16(&a, m, k, &w, &mut c16, false);
            // Alternated, so a change of load on a shared machine meets both.
            let (mut t32, mut t16) = (Vec::new(), Vec::new());
            for _ in 0..runs {
                let t = Instant::now();
                f32_gemm(&a, &b, &mut c32, m, k, n, threads);
                t32.push(t.elapsed().as_secs_f64());
                let t = Instant::now();
                matmul_bf16(&a, m, k, &w, &mut c16, false);
                t16.push(t.elapsed().as_secs_f64());
            }
            let best = |v: &[f64]| v.iter().copied().fold(f64::INFINITY, f64::min);
            let (b32, b16) = (best(&t32), best(&t16));
            let (s32, s16) = (crate::bench::median(t32), crate::bench::median(t16));
            let (mut num, mut den) = (0f64, 0f64);
            for (x, y) in c16.iter().zip(&c32) {
                num += (*x as f64 - *y as f64).powi(2);
                den += (*y as f64).powi(2);
            }
            format!(
                "{{\"m\":{m},\"k\":{k},\"n\":{n},\"f32_ms\":{:.2},\"bf16_ms\":{:.2},\"f32_best_ms\":{:.2},\"bf16_best_ms\":{:.2},\"f32_gflops\":{:.1},\"bf16_gflops\":{:.1},\"bf16_over_f32_time\":{:.3},\"pack_weights_ms\":{pack_ms:.2},\"rel_rms_vs_f32\":{:.2e}}}",
                s32 * 1e3,
                s16 * 1e3,
                b32 * 1e3,
                b16 * 1e3,
                flop / b32 / 1e9,
                flop / b16 / 1e9,
                b16 / b32,
                (num / den.max(f64::MIN_POSITIVE)).sqrt()
            )
        });
        rows.push(row);
    }
    out += &format!(",\"gemm\":[{}]}}", rows.join(","));
    Ok(out)
}
