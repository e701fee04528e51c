//! The fused CUDA kernels (cuda/fused.cu) compiled as C++ with crates/splat/cuda/emulate.h + cuda/emulate_half.h
//! and run on the CPU by cuda/emulate_main.cpp, with the launch sequence of src/fused_cuda.rs: GroupNorm(+SiLU)
//! against `norm::group_norm` on CPU f32 tensors, GEGLU against its closed form in f64, in f32, f16 and bf16.
//! Needs g++ (C++20); without it the tests fail, they do not skip.
//!
//! Error model (ε = 2⁻²⁴, the f32 unit roundoff; G = values per group):
//! - statistics: chunk sums in f32 (per-thread runs of ≤ 16, then a 256-way tree), merged in f64, so the mean
//!   is off by ≲ ε·√G·(σ + |mean|) and 1/std relatively by ≲ ε·√G·(1 + |mean|/σ); checked with 8·ε·√G·(…).
//! - f32 output y = (x − m)·(r·w) + b, SiLU: the statistics' error carried through |w|·(1 + |x̂|), plus a few
//!   roundings of the terms the CPU reference forms (x·a, mean·a, b, y): the CPU path computes
//!   x·a + (b − mean·a), which cancels; the kernel subtracts the mean first.
//! - f16 / bf16: the inputs are rounded to the dtype first and the reference runs on those rounded values, so
//!   the only extra error is the output's rounding, ≤ u·|y| (u = 2⁻¹¹ / 2⁻⁸) plus 2⁻²⁵ near f16's subnormals.
//! - GEGLU: y = a'·gelu(g'), a' = a + b_a, g' = g + b_g in f32; erff within 2 ulp, the cancellation of 1 + erf
//!   for negative g' leaves an absolute error ≲ ε·|g'| in gelu: tol = |a'|·6ε·(|gelu(g')| + |g'|) + 4ε·|y|.

use std::collections::HashMap;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use candle_core::{DType, Device, Tensor};
use mvsplat360_nn::norm::group_norm;

const EPS32: f64 = 1.0 / (1u64 << 24) as f64;

fn work_dir() -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("nn_cuda_emulated");
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The driver, built once per test process.
fn driver() -> &'static Path {
    static EXE: OnceLock<PathBuf> = OnceLock::new();
    EXE.get_or_init(|| {
        let src = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("cuda/emulate_main.cpp");
        let exe = work_dir().join("fused_emulate_main");
        let res = Command::new("g++").args(["-O2", "-std=c++20", "-pthread", "-Wall", "-Werror", "-o"]).arg(&exe).arg(&src).output();
        let out = match res {
            Ok(o) => o,
            Err(e) => panic!(
                "cannot run g++ ({e}): this test compiles cuda/fused.cu as C++20 with g++ (GCC >= 11); install g++ \
                 (e.g. apt-get install g++)"
            ),
        };
        assert!(out.status.success(), "g++ failed to build {}:\n{}", src.display(), String::from_utf8_lossy(&out.stderr));
        exe
    })
}

enum Arr {
    F(Vec<f32>),
    I(Vec<i32>),
}

fn write_records(path: &Path, recs: &[(&str, Arr)]) {
    let mut b = Vec::new();
    for (name, a) in recs {
        b.extend((name.len() as u32).to_le_bytes());
        b.extend(name.as_bytes());
        let (dtype, words): (u32, Vec<u32>) = match a {
            Arr::F(v) => (0, v.iter().map(|x| x.to_bits()).collect()),
            Arr::I(v) => (1, v.iter().map(|&x| x as u32).collect()),
        };
        b.extend(dtype.to_le_bytes());
        b.extend((words.len() as u64).to_le_bytes());
        for w in words {
            b.extend(w.to_le_bytes());
        }
    }
    std::fs::File::create(path).unwrap().write_all(&b).unwrap();
}

/// name → f32 values (the driver writes f32 only).
fn read_records(path: &Path) -> HashMap<String, Vec<f32>> {
    let mut b = Vec::new();
    std::fs::File::open(path).unwrap().read_to_end(&mut b).unwrap();
    let mut out = HashMap::new();
    let mut p = 0;
    let u32_at = |p: usize| u32::from_le_bytes(b[p..p + 4].try_into().unwrap());
    while p < b.len() {
        let len = u32_at(p) as usize;
        let name = String::from_utf8(b[p + 4..p + 4 + len].to_vec()).unwrap();
        p += 4 + len;
        assert_eq!(u32_at(p), 0, "{name}: not f32");
        let count = u64::from_le_bytes(b[p + 4..p + 12].try_into().unwrap()) as usize;
        p += 12;
        out.insert(name, (0..count).map(|k| f32::from_bits(u32_at(p + 4 * k))).collect());
        p += 4 * count;
    }
    out
}

fn emulate(tag: &str, recs: &[(&str, Arr)]) -> HashMap<String, Vec<f32>> {
    let dir = work_dir();
    let (inp, out) = (dir.join(format!("{tag}.in")), dir.join(format!("{tag}.out")));
    write_records(&inp, recs);
    let t0 = std::time::Instant::now();
    let res = Command::new(driver()).arg(&inp).arg(&out).output().unwrap();
    assert!(res.status.success(), "emulate_main failed ({tag}): {}", String::from_utf8_lossy(&res.stderr));
    eprintln!("{tag}: emulated in {:.2} s", t0.elapsed().as_secs_f64());
    read_records(&out)
}

/// Deterministic normal numbers (LCG + Box–Muller).
struct Rng(u64);

impl Rng {
    fn uni(&mut self) -> f64 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    fn normal(&mut self, mean: f32, std: f32, n: usize) -> Vec<f32> {
        (0..n).map(|_| mean + std * ((-2.0 * self.uni().ln()).sqrt() * (std::f64::consts::TAU * self.uni()).cos()) as f32).collect()
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Dt {
    F32,
    F16,
    Bf16,
}

impl Dt {
    fn code(self) -> i32 {
        self as i32
    }

    /// Unit roundoff of the dtype.
    fn u(self) -> f64 {
        match self {
            Dt::F32 => EPS32,
            Dt::F16 => 1.0 / 2048.0,
            Dt::Bf16 => 1.0 / 256.0,
        }
    }

    /// `v` rounded to the dtype (by candle, independently of emulate_half.h) and back to f32.
    fn round(self, v: &[f32]) -> Vec<f32> {
        let dt = match self {
            Dt::F32 => return v.to_vec(),
            Dt::F16 => DType::F16,
            Dt::Bf16 => DType::BF16,
        };
        Tensor::new(v, &Device::Cpu).unwrap().to_dtype(dt).unwrap().to_dtype(DType::F32).unwrap().to_vec1().unwrap()
    }
}

struct GnCase {
    seed: u64,
    dt: Dt,
    /// (n, c, s, groups, frames)
    dims: (usize, usize, usize, usize, usize),
    silu: bool,
    chunk: usize,
    /// Mean and std of x.
    dist: (f32, f32),
}

/// Worst err/tol over the outputs and the statistics.
fn run_group_norm(case: &GnCase) -> f64 {
    let (n, c, s, groups, frames) = case.dims;
    let (cg, bn) = (c / groups, n / frames);
    let mut rng = Rng(case.seed);
    let x = case.dt.round(&rng.normal(case.dist.0, case.dist.1, n * c * s));
    let w = rng.normal(1.0, 0.5, c);
    let b = rng.normal(0.0, 0.5, c);
    let eps = 1e-5f32;
    let tag = format!("gn_{:?}_{n}x{c}x{s}_g{groups}_f{frames}_silu{}_chunk{}_seed{}", case.dt, case.silu as u8, case.chunk, case.seed);
    let dims = vec![n as i32, c as i32, s as i32, groups as i32, frames as i32, case.silu as i32, case.chunk as i32];
    let out = emulate(
        &tag,
        &[
            ("op", Arr::I(vec![0])),
            ("dtype", Arr::I(vec![case.dt.code()])),
            ("dims", Arr::I(dims)),
            ("eps", Arr::F(vec![eps])),
            ("x", Arr::F(x.clone())),
            ("weight", Arr::F(w.clone())),
            ("bias", Arr::F(b.clone())),
        ],
    );
    let (y, stats) = (&out["y"], &out["stats"]);
    assert_eq!(y.len(), x.len(), "{tag}: output size");
    assert_eq!(stats.len(), 2 * bn * groups, "{tag}: stats size");

    // Statistics in f64, pooled over the frames of each batch item.
    let gsize = (frames * cg * s) as f64;
    let sq = gsize.sqrt();
    let mut ref_stats = vec![(0f64, 0f64); bn * groups];
    let mut worst: f64 = 0.0;
    for bi in 0..bn {
        for g in 0..groups {
            let vals = || (0..frames).flat_map(move |f| ((bi * frames + f) * c + g * cg) * s..((bi * frames + f) * c + (g + 1) * cg) * s);
            let mean = vals().map(|i| x[i] as f64).sum::<f64>() / gsize;
            let var = vals().map(|i| (x[i] as f64 - mean).powi(2)).sum::<f64>() / gsize;
            let rstd = 1.0 / (var + eps as f64).sqrt();
            let sigma = var.sqrt();
            let k = bi * groups + g;
            ref_stats[k] = (mean, rstd);
            let tol_m = 8.0 * EPS32 * sq * (sigma + mean.abs());
            let tol_r = 8.0 * EPS32 * sq * (1.0 + mean.abs() / sigma) * rstd;
            let (em, er) = ((stats[2 * k] as f64 - mean).abs(), (stats[2 * k + 1] as f64 - rstd).abs());
            assert!(
                em <= tol_m && er <= tol_r,
                "{tag}: group ({bi}, {g}) mean {} vs {mean} (tol {tol_m:e}), rstd {} vs {rstd} (tol {tol_r:e})",
                stats[2 * k],
                stats[2 * k + 1]
            );
            worst = worst.max(em / tol_m).max(er / tol_r);
        }
    }

    // The CPU path on the same (rounded) inputs.
    let dev = Device::Cpu;
    let xt = Tensor::from_vec(x.clone(), (n, c, s), &dev).unwrap();
    let (wt, bt) = (Tensor::new(w.as_slice(), &dev).unwrap(), Tensor::new(b.as_slice(), &dev).unwrap());
    let yr: Vec<f32> = group_norm(&xt, groups, frames, &wt, &bt, eps as f64, case.silu).unwrap().flatten_all().unwrap().to_vec1().unwrap();
    let (mut max_err, mut worst_y) = (0f64, 0f64);
    for i in 0..x.len() {
        let ch = (i / s) % c;
        let item = i / (c * s);
        let (mean, rstd) = ref_stats[(item / frames) * groups + ch / cg];
        let (xi, wc, bc) = (x[i] as f64, w[ch].abs() as f64, b[ch].abs() as f64);
        let xhat = ((xi - mean) * rstd).abs();
        let a = rstd * wc;
        let stat_err = 8.0 * EPS32 * sq * (1.0 + mean.abs() * rstd) * (1.0 + xhat) * wc;
        let round_err = 4.0 * EPS32 * (xi.abs() * a + mean.abs() * a + bc);
        let (yr_i, y_i) = (yr[i] as f64, y[i] as f64);
        let tol = 1.1 * (stat_err + round_err) + 4.0 * EPS32 * yr_i.abs() + case.dt.u() * yr_i.abs() + if case.dt == Dt::F16 { 2f64.powi(-25) } else { 0.0 };
        let err = (y_i - yr_i).abs();
        assert!(err <= tol && y_i.is_finite(), "{tag}: element {i} (item {item}, channel {ch}): emulated {y_i} vs CPU {yr_i}, |diff| {err:e} > tol {tol:e}");
        max_err = max_err.max(err);
        worst_y = worst_y.max(err / tol);
    }
    eprintln!("{tag}: max |y − cpu| {max_err:.3e}, worst err/tol: outputs {worst_y:.3}, statistics {worst:.3}");
    worst.max(worst_y)
}

#[test]
fn emulated_group_norm_matches_cpu() {
    let cases = [
        // frames > 1 pooled, cg = 2, S not a multiple of the block, one chunk per run.
        GnCase { seed: 1, dt: Dt::F32, dims: (6, 8, 1000, 4, 3), silu: true, chunk: 4096, dist: (0.5, 1.0) },
        // cg = 1, many chunks per run with a 9-value tail (777 = 3·256 + 9), large mean: the merge's conditioning.
        GnCase { seed: 2, dt: Dt::F32, dims: (1, 4, 777, 4, 1), silu: false, chunk: 256, dist: (20.0, 0.5) },
        // Full 4096 chunks and a partial one (run of 6000), frames 2.
        GnCase { seed: 3, dt: Dt::F16, dims: (4, 4, 3000, 2, 2), silu: true, chunk: 4096, dist: (-0.3, 2.0) },
        GnCase { seed: 4, dt: Dt::Bf16, dims: (2, 6, 500, 3, 2), silu: true, chunk: 1000, dist: (0.2, 1.5) },
        GnCase { seed: 5, dt: Dt::Bf16, dims: (3, 3, 130, 3, 1), silu: false, chunk: 4096, dist: (1.0, 0.1) },
        GnCase { seed: 6, dt: Dt::F16, dims: (2, 4, 45, 1, 2), silu: false, chunk: 100, dist: (0.0, 3.0) },
    ];
    for case in &cases {
        run_group_norm(case);
    }
}

fn erf_gelu(g: f64) -> f64 {
    0.5 * g * (1.0 + candle_core::cpu::erf::erf_f64(g * std::f64::consts::FRAC_1_SQRT_2))
}

#[test]
fn emulated_geglu_matches_closed_form() {
    for (seed, dt, rows, hdim, with_bias) in
        [(11u64, Dt::F32, 7usize, 300usize, true), (12, Dt::F16, 5, 257, true), (13, Dt::Bf16, 3, 600, true), (14, Dt::F32, 4, 64, false)]
    {
        let mut rng = Rng(seed);
        let h = dt.round(&rng.normal(0.0, 2.5, rows * 2 * hdim));
        let bias = rng.normal(0.0, 0.5, 2 * hdim);
        let tag = format!("geglu_{dt:?}_{rows}x{hdim}_bias{}", with_bias as u8);
        let mut recs = vec![
            ("op", Arr::I(vec![1])),
            ("dtype", Arr::I(vec![dt.code()])),
            ("dims", Arr::I(vec![rows as i32, hdim as i32, with_bias as i32])),
            ("h", Arr::F(h.clone())),
        ];
        if with_bias {
            recs.push(("bias", Arr::F(bias.clone())));
        }
        let y = &emulate(&tag, &recs)["y"];
        assert_eq!(y.len(), rows * hdim);
        let (mut max_err, mut worst) = (0f64, 0f64);
        for r in 0..rows {
            for j in 0..hdim {
                let (bv, bg) = if with_bias { (bias[j] as f64, bias[hdim + j] as f64) } else { (0.0, 0.0) };
                // First half the value, second half the gate (diffusers/sgm `GEGLU`).
                let a = h[r * 2 * hdim + j] as f64 + bv;
                let g = h[r * 2 * hdim + hdim + j] as f64 + bg;
                let yr = a * erf_gelu(g);
                let tol = a.abs() * 6.0 * EPS32 * (erf_gelu(g).abs() + g.abs())
                    + 4.0 * EPS32 * yr.abs()
                    + dt.u() * yr.abs()
                    + if dt == Dt::F16 { 2f64.powi(-25) } else { 0.0 };
                let err = (y[r * hdim + j] as f64 - yr).abs();
                assert!(err <= tol, "{tag}: ({r}, {j}): emulated {} vs {yr}, |diff| {err:e} > tol {tol:e}", y[r * hdim + j]);
                max_err = max_err.max(err);
                worst = worst.max(err / tol);
            }
        }
        eprintln!("{tag}: max |y − ref| {max_err:.3e}, worst err/tol {worst:.3}");
    }
}
