//! The CUDA kernels (cuda/rasterize.cu) compiled as C++ with cuda/emulate.h and run by cuda/emulate_main.cpp
//! on the CPU: every output must match our CPU rasterizer and the golden fixtures, via both the cov3d and the
//! scales+quats paths. Also: GradMode::Exact against the CPU path, a synthetic scene with many clamped
//! Jacobians (which the fixtures barely exercise), an all-culled scene (no pairs), and the medium fixture
//! with FMA contraction as nvcc does by default. Needs g++ (C++20); without it the tests fail, they do not
//! skip.
//!
//! Tolerances: images 1e-4 abs, per-Gaussian projections 1e-5 x max, gradients element-wise
//! |a − b| ≤ 3e-5·max|ref| + 1e-4·|ref| (tests/parity.rs's rule; before: 1e-4 × max |ref| for the largest
//! difference), radii / tiles_touched / pair lists exact, n_contrib up to 5 pixels (f32 rounding may flip the
//! T < 1e-4 stop).

use std::collections::HashMap;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use mvsplat360_splat::cpu::{self, CovInput, GradMode, PixelGrads, RasterInputs, RasterSettings};
use mvsplat360_splat::RasterCamera;
use mvsplat360_testkit::get;

mod common;
use common::{check_abs, check_close, check_rel, count_diff, max_abs, to_planar, v32, vi, CovPath, Fixture};

const TILE: usize = 16;

// ---- the driver's record files (see emulate_main.cpp) ----

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

/// name → (dtype, raw 32-bit words)
fn read_records(path: &Path) -> HashMap<String, (u32, Vec<u32>)> {
    let mut b = Vec::new();
    std::fs::File::open(path).unwrap().read_to_end(&mut b).unwrap();
    let mut out = HashMap::new();
    let mut p = 0;
    let u32_at = |p: usize| u32::from_le_bytes(b[p..p + 4].try_into().unwrap());
    while p < b.len() {
        let len = u32_at(p) as usize;
        let name = String::from_utf8(b[p + 4..p + 4 + len].to_vec()).unwrap();
        p += 4 + len;
        let dtype = u32_at(p);
        let count = u64::from_le_bytes(b[p + 4..p + 12].try_into().unwrap()) as usize;
        p += 12;
        let words = (0..count).map(|k| u32_at(p + 4 * k)).collect();
        p += 4 * count;
        out.insert(name, (dtype, words));
    }
    out
}

struct Out(HashMap<String, (u32, Vec<u32>)>);

impl Out {
    fn raw(&self, name: &str, dtype: u32) -> &[u32] {
        let (d, v) = self.0.get(name).unwrap_or_else(|| panic!("driver wrote no `{name}`"));
        assert_eq!(*d, dtype, "{name}: dtype");
        v
    }
    fn f(&self, name: &str) -> Vec<f32> {
        self.raw(name, 0).iter().map(|&w| f32::from_bits(w)).collect()
    }
    fn i(&self, name: &str) -> Vec<i64> {
        self.raw(name, 1).iter().map(|&w| w as i32 as i64).collect()
    }
    fn u(&self, name: &str) -> Vec<u32> {
        self.raw(name, 2).to_vec()
    }
}

fn work_dir() -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("cuda_emulated");
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// How the driver is compiled.
#[derive(Clone, Copy, PartialEq)]
enum Build {
    /// No FMA contraction (baseline x86-64): the plain C++ semantics of the kernels.
    Plain,
    /// `-march=native -ffp-contract=fast`: a*b+c contracted into FMA where the CPU has it, like nvcc's
    /// default, to check that the tolerances absorb GPU-style rounding.
    Fma,
}

/// Build cuda/emulate_main.cpp once per test process and flavour.
fn driver(build: Build) -> &'static Path {
    static PLAIN: OnceLock<PathBuf> = OnceLock::new();
    static FMA: OnceLock<PathBuf> = OnceLock::new();
    let (cell, name, extra): (_, _, &[&str]) = match build {
        Build::Plain => (&PLAIN, "emulate_main", &[]),
        Build::Fma => (&FMA, "emulate_main_fma", &["-march=native", "-ffp-contract=fast"]),
    };
    cell.get_or_init(|| {
        let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("cuda/emulate_main.cpp");
        let exe = work_dir().join(name);
        let res = Command::new("g++").args(["-O2", "-std=c++20", "-pthread", "-Wall", "-Werror"]).args(extra).arg("-o").arg(&exe).arg(&src).output();
        let out = match res {
            Ok(o) => o,
            Err(e) => panic!(
                "cannot run g++ ({e}): this test compiles cuda/rasterize.cu as C++20 with g++ (GCC >= 11); \
                 install g++ (e.g. apt-get install g++)"
            ),
        };
        assert!(out.status.success(), "g++ failed to build {}:\n{}", src.display(), String::from_utf8_lossy(&out.stderr));
        exe
    })
}

// ---- comparisons ----
/// The (tile, depth, Gaussian id)-sorted pair list implied by the driver's own radii / means2d / depths.
fn expected_pairs(radii: &[i64], m2: &[f32], depths: &[f32], w: usize, h: usize) -> Vec<u32> {
    let grid = [w.div_ceil(TILE), h.div_ceil(TILE)];
    let cl = |v: f32, g: usize| -> usize { (v as i32).clamp(0, g as i32) as usize };
    let mut pairs = Vec::new();
    for (i, &r) in radii.iter().enumerate() {
        if r <= 0 {
            continue;
        }
        let (r, b) = (r as f32, TILE as f32);
        let (x, y) = (m2[2 * i], m2[2 * i + 1]);
        for ty in cl((y - r) / b, grid[1])..cl((y + r + b - 1.0) / b, grid[1]) {
            for tx in cl((x - r) / b, grid[0])..cl((x + r + b - 1.0) / b, grid[0]) {
                pairs.push((ty * grid[0] + tx, depths[i].to_bits(), i as u32));
            }
        }
    }
    pairs.sort_unstable();
    pairs.into_iter().map(|p| p.2).collect()
}

/// Camera and background as the kernels' `params` array (P_* layout of rasterize.cu).
fn params_of(s: &RasterSettings) -> Vec<f32> {
    let cam = &s.camera;
    let mut p: Vec<f32> = Vec::with_capacity(42);
    p.extend(cam.viewmatrix.iter().flatten());
    p.extend(cam.full_proj().iter().flatten());
    p.extend(cam.campos());
    p.extend(cam.focal());
    p.extend(cam.tanfov());
    p.extend(s.background);
    assert_eq!(p.len(), 42);
    p
}

/// Forward + backward of the emulated CUDA kernels.
fn emulate(build: Build, inp: &RasterInputs, s: &RasterSettings, pg: &PixelGrads, mode: GradMode, tag: &str) -> Out {
    let (w, h) = (s.camera.width, s.camera.height);
    let dims = [inp.len(), w, h, inp.sh_coeffs, inp.eval_degree(), inp.num_features];
    let mut recs = vec![
        ("dims", Arr::I(dims.iter().map(|&d| d as i32).collect())),
        ("params", Arr::F(params_of(s))),
        ("means", Arr::F(inp.means.to_vec())),
        ("opacities", Arr::F(inp.opacities.to_vec())),
        ("sh", Arr::F(inp.sh.to_vec())),
        ("features", Arr::F(inp.features.to_vec())),
        ("dl_rgb", Arr::F(pg.rgb.to_vec())),
        ("dl_feat", Arr::F(pg.features.to_vec())),
        ("exact", Arr::I(vec![(mode == GradMode::Exact) as i32])),
    ];
    if let Some(a) = pg.alpha {
        recs.push(("dl_alpha", Arr::F(a.to_vec())));
    }
    if let Some(d) = pg.depth {
        recs.push(("dl_depth", Arr::F(d.to_vec())));
    }
    match inp.cov {
        CovInput::Cov3d(c) => recs.push(("cov3d", Arr::F(c.to_vec()))),
        CovInput::ScaleRot { scales, quats } => {
            recs.push(("scales", Arr::F(scales.to_vec())));
            recs.push(("quats", Arr::F(quats.to_vec())));
        }
    }
    let (in_path, out_path) = (work_dir().join(format!("{tag}.in")), work_dir().join(format!("{tag}.out")));
    write_records(&in_path, &recs);
    let t0 = std::time::Instant::now();
    let res = Command::new(driver(build)).arg(&in_path).arg(&out_path).output().unwrap();
    assert!(res.status.success(), "emulate_main failed: {}", String::from_utf8_lossy(&res.stderr));
    eprintln!("emulated CUDA run ({tag}): {:.2} s", t0.elapsed().as_secs_f64());
    Out(read_records(&out_path))
}

/// Every emulated output against our CPU rasterizer; returns the CPU results.
fn check_vs_cpu(g: &Out, inp: &RasterInputs, s: &RasterSettings, pg: &PixelGrads, mode: GradMode) -> (cpu::ForwardOutput, cpu::Gradients) {
    let (w, h) = (s.camera.width, s.camera.height);
    let out = cpu::forward(inp, s).unwrap();
    let cg = cpu::backward(inp, s, &out, pg, mode).unwrap();

    // Discrete outputs and the binning (scan, duplicate, bitonic sort, ranges).
    let radii = g.i("radii");
    let cpu_radii: Vec<i64> = out.radii.iter().map(|&r| r as i64).collect();
    assert_eq!(radii, cpu_radii, "radii vs CPU");
    let tt = g.u("tiles_touched");
    assert_eq!(tt, out.tiles_touched, "tiles_touched vs CPU");
    let pairs = g.u("num_pairs")[0] as usize;
    assert_eq!(pairs, out.num_pairs(), "pair count vs CPU");
    assert_eq!(pairs as u64, tt.iter().map(|&t| t as u64).sum::<u64>(), "pair count vs scan");
    let (m2, depths) = (g.f("means2d"), g.f("depths"));
    assert_eq!(g.u("point_list"), expected_pairs(&radii, &m2, &depths, w, h), "sorted pair list");
    let bad = count_diff(&g.u("n_contrib"), &out.n_contrib);
    eprintln!("n_contrib: {bad} pixels differ from CPU");
    assert!(bad <= 5, "n_contrib differs from CPU at {bad} pixels");

    for (name, got, cpu_v) in
        [("means2d", &m2, &out.means2d), ("depths", &depths, &out.depths), ("cov2d", &g.f("cov2d"), &out.cov2d), ("conic", &g.f("conic"), &out.conic)]
    {
        check_rel(&format!("{name} vs CPU"), got, cpu_v, 1e-5);
    }
    check_abs("colors vs CPU", &g.f("colors"), &out.colors, 1e-5);
    for (name, got, cpu_v) in [
        ("rgb", g.f("rgb"), &out.rgb),
        ("feat", g.f("feat"), &out.features),
        ("alpha", g.f("alpha"), &out.alpha),
        ("depth", g.f("depth"), &out.depth),
        ("final_T", g.f("final_t"), &out.final_t),
    ] {
        check_abs(&format!("{name} vs CPU"), &got, cpu_v, 1e-4);
    }
    for (name, got, cpu_v) in grads_of(g, &cg, inp) {
        check_grad(&format!("{name} vs CPU"), &got, cpu_v);
    }
    (out, cg)
}

/// Gradients element-wise: |a − b| ≤ GRAD_ATOL·max|b| + GRAD_RTOL·|b|, as tests/parity.rs.
const GRAD_ATOL: f64 = 3e-5;
const GRAD_RTOL: f64 = 1e-4;

fn check_grad(name: &str, got: &[f32], want: &[f32]) {
    check_close(name, got, want, GRAD_ATOL * max_abs(want), GRAD_RTOL);
}

/// (fixture name, emulated, CPU) for every gradient of this input path.
fn grads_of<'a>(g: &Out, cg: &'a cpu::Gradients, inp: &RasterInputs) -> Vec<(&'static str, Vec<f32>, &'a [f32])> {
    let mut v: Vec<(&str, Vec<f32>, &[f32])> = vec![
        ("grad_means", g.f("grad_means"), &cg.means),
        ("grad_opacities", g.f("grad_opacities"), &cg.opacities),
        ("grad_sh", g.f("grad_sh"), &cg.sh),
        ("grad_features", g.f("grad_features"), &cg.features),
        ("grad_means2d_ndc", g.f("grad_means2d_ndc"), &cg.means2d_ndc),
        ("grad_cov3d", g.f("grad_cov3d"), &cg.cov3d),
    ];
    if let CovInput::ScaleRot { .. } = inp.cov {
        v.push(("grad_scales", g.f("grad_scales"), cg.scales.as_deref().unwrap()));
        v.push(("grad_quats", g.f("grad_quats"), cg.quats.as_deref().unwrap()));
    }
    v
}

/// The fixture's scene through both covariance inputs; with [`GradMode::Exact`] (random alpha / depth pixel
/// gradients added) the gradients are compared with the CPU path only (the fixture holds official ones).
fn run(file: &str, build: Build, mode: GradMode) {
    let fx = Fixture::load(file);
    let m = &fx.m;
    let settings = fx.settings;
    let (h, w, nf) = (settings.camera.height, settings.camera.width, fx.nf);
    let (w1, w2) = (&fx.w1, &fx.w2);
    let mut rng = Lcg(7);
    let da: Vec<f32> = (0..h * w).map(|_| rng.uni(-1.0, 1.0)).collect();
    let dd: Vec<f32> = (0..h * w).map(|_| rng.uni(-1.0, 1.0)).collect();
    let exact = mode == GradMode::Exact;
    let pg = PixelGrads { rgb: w1, features: w2, alpha: exact.then_some(&da[..]), depth: exact.then_some(&dd[..]) };
    let n = fx.opacities.len();

    let fx_radii = vi(get(m, "radii"));
    let vis: Vec<bool> = fx_radii.iter().map(|&r| r > 0).collect();
    let sel = |v: &[f32], c: usize| -> Vec<f32> { v.chunks(c).zip(&vis).filter(|(_, &ok)| ok).flat_map(|(x, _)| x.to_vec()).collect() };

    for path in [CovPath::Cov3d, CovPath::ScaleRot] {
        let inp = fx.inputs(path);
        let path = if path == CovPath::Cov3d { "cov" } else { "sr" };
        eprintln!("--- {file} via {path}");
        let flavour = match (build, mode) {
            (Build::Fma, _) => "_fma",
            (_, GradMode::Exact) => "_exact",
            _ => "",
        };
        let tag = format!("{}_{path}{flavour}", file.trim_end_matches(".safetensors"));
        let g = emulate(build, &inp, &settings, &pg, mode, &tag);
        let (_, cg) = check_vs_cpu(&g, &inp, &settings, &pg, mode);

        // Against the fixture (projections of visible Gaussians only: culled ones are unspecified there).
        assert_eq!(g.i("radii"), fx_radii, "radii vs fixture");
        let tt = g.u("tiles_touched");
        let tt_ref = vi(get(m, "tiles_touched"));
        let tt_bad = (0..n).filter(|&i| vis[i] && tt[i] as i64 != tt_ref[i]).count();
        assert_eq!(tt_bad, 0, "tiles_touched vs fixture differ for {tt_bad} visible Gaussians");
        let nc_ref: Vec<u32> = vi(get(m, "n_contrib")).iter().map(|&x| x as u32).collect();
        let bad = count_diff(&g.u("n_contrib"), &nc_ref);
        eprintln!("n_contrib: {bad} pixels differ from fixture");
        assert!(bad <= 5, "n_contrib differs from fixture at {bad} pixels");
        for (name, c) in [("means2d", 2), ("depths", 1), ("cov2d", 3), ("conic", 3)] {
            check_rel(&format!("{name} vs fixture"), &sel(&g.f(name), c), &sel(&v32(get(m, name)), c), 1e-5);
        }
        check_abs("colors vs fixture", &sel(&g.f("colors"), 3), &sel(&v32(get(m, "colors")), 3), 1e-5);
        for (name, fx_name, c) in [("rgb", "rgb", 3), ("feat", "feat", nf), ("alpha", "alpha", 1), ("depth", "depth", 1), ("final_t", "final_T", 1)] {
            check_abs(&format!("{name} vs fixture"), &g.f(name), &to_planar(&v32(get(m, fx_name)), h, w, c), 1e-4);
        }
        if !exact {
            for (name, got, _) in grads_of(&g, &cg, &inp) {
                check_grad(&format!("{name} vs fixture"), &got, &v32(get(m, name)));
            }
        }
    }
}

/// Deterministic uniform numbers for the synthetic scenes.
struct Lcg(u64);

impl Lcg {
    fn uni(&mut self, lo: f32, hi: f32) -> f32 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        lo + (hi - lo) * ((self.0 >> 40) as f32 / (1u64 << 24) as f32)
    }
}

struct Scene {
    means: Vec<f32>,
    scales: Vec<f32>,
    quats: Vec<f32>,
    cov3d: Vec<f32>,
    opac: Vec<f32>,
    sh: Vec<f32>,
    feats: Vec<f32>,
    w1: Vec<f32>,
    w2: Vec<f32>,
    /// Alpha / depth pixel gradients (exact mode).
    da: Vec<f32>,
    dd: Vec<f32>,
    settings: RasterSettings,
}

const SYN_K: usize = 9;
const SYN_NF: usize = 3;

/// A scene the fixtures exercise little: many visible Gaussians outside the 1.3 tan(fov) cone (clamped
/// Jacobian), an image size that is no multiple of 16, an off-centre principal point, a rotated camera, SH
/// degree 2, 3 feature channels, opacities of exactly 1 (the 0.99 clamp), culled and off-image Gaussians.
/// With `culled_only`, every Gaussian is behind the camera (no pairs at all).
fn synthetic(n: usize, culled_only: bool) -> Scene {
    let (w, h) = (70usize, 45usize);
    let (fx, fy) = (50f32, 48f32);
    let (tanx, tany) = (w as f32 / (2.0 * fx), h as f32 / (2.0 * fy));
    // View = rotation about y then x, plus a translation.
    let (a, b) = (0.2f32, -0.1f32);
    let ry = [[a.cos(), 0.0, a.sin()], [0.0, 1.0, 0.0], [-a.sin(), 0.0, a.cos()]];
    let rx = [[1.0, 0.0, 0.0], [0.0, b.cos(), -b.sin()], [0.0, b.sin(), b.cos()]];
    let mut r = [[0f32; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            r[i][j] = (0..3).map(|k| rx[i][k] * ry[k][j]).sum();
        }
    }
    let t = [0.3f32, -0.2, 0.5];
    let mut view = [[0f32; 4]; 4];
    for i in 0..3 {
        view[i][..3].copy_from_slice(&r[i]);
        view[i][3] = t[i];
    }
    view[3][3] = 1.0;
    let camera = RasterCamera { viewmatrix: view, fx, fy, cx: 0.5 * w as f32 + 1.5, cy: 0.5 * h as f32 - 1.0, width: w, height: h, near: 0.01, far: 100.0 };
    let mut rng = Lcg(0x5eed_cafe);
    let mut sc = Scene {
        means: Vec::new(),
        scales: Vec::new(),
        quats: Vec::new(),
        cov3d: Vec::new(),
        opac: Vec::new(),
        sh: (0..n * SYN_K * 3).map(|_| rng.uni(-0.5, 0.5)).collect(),
        feats: (0..n * SYN_NF).map(|_| rng.uni(-1.0, 1.0)).collect(),
        w1: (0..3 * w * h).map(|_| rng.uni(-1.0, 1.0)).collect(),
        w2: (0..SYN_NF * w * h).map(|_| rng.uni(-1.0, 1.0)).collect(),
        da: (0..w * h).map(|_| rng.uni(-1.0, 1.0)).collect(),
        dd: (0..w * h).map(|_| rng.uni(-1.0, 1.0)).collect(),
        settings: RasterSettings { camera, background: [0.3, 0.1, 0.7] },
    };
    for i in 0..n {
        let kind = rng.uni(0.0, 1.0);
        let z = rng.uni(2.0, 8.0);
        let (mut x, mut y) = (rng.uni(-0.9, 0.9) * tanx * z, rng.uni(-0.9, 0.9) * tany * z);
        let mut s = [0f32; 3];
        for sk in &mut s {
            *sk = 0.01 * 10f32.powf(rng.uni(0.0, 1.0));
        }
        let side = if rng.uni(0.0, 1.0) < 0.5 { -1.0 } else { 1.0 };
        let zc = if culled_only {
            rng.uni(-2.0, 0.2)
        } else if kind < 0.06 {
            // Outside the cone in x, large enough to reach the image.
            x = side * rng.uni(1.35, 1.8) * tanx * z;
            s = s.map(|v| v * 12.0);
            z
        } else if kind < 0.12 {
            y = side * rng.uni(1.35, 1.8) * tany * z;
            s = s.map(|v| v * 12.0);
            z
        } else if kind < 0.17 {
            rng.uni(-1.0, 0.2)
        } else if kind < 0.2 {
            // Far off the image and small: empty tile rectangle.
            x = side * 6.0 * tanx * z;
            z
        } else {
            z
        };
        // World point = R^T (p_cam - t).
        let pc = [x - t[0], y - t[1], zc - t[2]];
        sc.means.extend((0..3).map(|j| r[0][j] * pc[0] + r[1][j] * pc[1] + r[2][j] * pc[2]));
        let mut q = [rng.uni(-1.0, 1.0), rng.uni(-1.0, 1.0), rng.uni(-1.0, 1.0), rng.uni(-1.0, 1.0)];
        let qn = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-3);
        q = q.map(|v| v / qn);
        let rot = {
            let [w_, x_, y_, z_] = q;
            [
                [1.0 - 2.0 * (y_ * y_ + z_ * z_), 2.0 * (x_ * y_ - w_ * z_), 2.0 * (x_ * z_ + w_ * y_)],
                [2.0 * (x_ * y_ + w_ * z_), 1.0 - 2.0 * (x_ * x_ + z_ * z_), 2.0 * (y_ * z_ - w_ * x_)],
                [2.0 * (x_ * z_ - w_ * y_), 2.0 * (y_ * z_ + w_ * x_), 1.0 - 2.0 * (x_ * x_ + y_ * y_)],
            ]
        };
        for (u, v) in [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)] {
            sc.cov3d.push((0..3).map(|k| rot[u][k] * rot[v][k] * s[k] * s[k]).sum());
        }
        sc.scales.extend(s);
        sc.quats.extend(q);
        sc.opac.push(if i % 17 == 0 { 1.0 } else { rng.uni(0.05, 0.8) });
    }
    sc
}

fn run_synthetic(culled_only: bool) {
    let sc = synthetic(500, culled_only);
    let s = &sc.settings;
    let (w, h) = (s.camera.width, s.camera.height);
    for (path, cov) in [("cov", CovInput::Cov3d(&sc.cov3d)), ("sr", CovInput::ScaleRot { scales: &sc.scales, quats: &sc.quats })] {
        let inp =
            RasterInputs { means: &sc.means, cov, opacities: &sc.opac, sh: &sc.sh, sh_coeffs: SYN_K, sh_degree: 2, features: &sc.feats, num_features: SYN_NF };
        let tag = format!("synthetic_{}_{path}", if culled_only { "culled" } else { "clamped" });
        eprintln!("--- {tag}");
        let official = PixelGrads { rgb: &sc.w1, features: &sc.w2, alpha: None, depth: None };
        let g = emulate(Build::Plain, &inp, s, &official, GradMode::Official, &tag);
        if culled_only {
            // Nothing visible: no pairs, background only, zero gradients.
            assert!(g.i("radii").iter().all(|&r| r == 0));
            assert_eq!(g.u("num_pairs"), vec![0]);
            let rgb = g.f("rgb");
            for ch in 0..3 {
                assert!(rgb[ch * w * h..(ch + 1) * w * h].iter().all(|&v| v == s.background[ch]));
            }
            assert!(g.f("feat").iter().all(|&v| v == 0.0));
            assert!(g.f("final_t").iter().all(|&v| v == 1.0));
            let mut names = vec!["grad_means", "grad_opacities", "grad_sh", "grad_features", "grad_means2d_ndc", "grad_cov3d"];
            if path == "sr" {
                names.extend(["grad_scales", "grad_quats"]);
            }
            for name in names {
                assert!(g.f(name).iter().all(|&v| v == 0.0), "{name} not zero");
            }
            continue;
        }
        check_vs_cpu(&g, &inp, s, &official, GradMode::Official);
        let exact = PixelGrads { rgb: &sc.w1, features: &sc.w2, alpha: Some(&sc.da), depth: Some(&sc.dd) };
        eprintln!("--- {tag} exact");
        let ge = emulate(Build::Plain, &inp, s, &exact, GradMode::Exact, &format!("{tag}_exact"));
        check_vs_cpu(&ge, &inp, s, &exact, GradMode::Exact);
        // The scene must really exercise the clamped Jacobian and the 0.99 clamp.
        let radii = g.i("radii");
        let v = &s.camera.viewmatrix;
        let tf = s.camera.tanfov();
        let clamped = (0..sc.opac.len())
            .filter(|&i| {
                let p = &sc.means[3 * i..3 * i + 3];
                let tv: Vec<f32> = (0..3).map(|r| v[r][0] * p[0] + v[r][1] * p[1] + v[r][2] * p[2] + v[r][3]).collect();
                radii[i] > 0 && ((tv[0] / tv[2]).abs() > 1.3 * tf[0] || (tv[1] / tv[2]).abs() > 1.3 * tf[1])
            })
            .count();
        let visible = radii.iter().filter(|&&r| r > 0).count();
        let opaque = (0..sc.opac.len()).filter(|&i| radii[i] > 0 && sc.opac[i] == 1.0).count();
        assert!(opaque >= 10, "only {opaque} visible Gaussians with opacity 1");
        let ft = g.f("final_t");
        let see_through = ft.iter().filter(|&&t| t > 0.05).count();
        eprintln!("{visible} visible Gaussians, {clamped} with a clamped Jacobian; {see_through} pixels with T > 0.05");
        assert!(clamped >= 30 && visible >= 350, "scene too tame: {visible} visible, {clamped} clamped");
        assert!(see_through >= w * h / 10, "scene too opaque: {see_through} pixels with T > 0.05");
        assert!(g.u("n_contrib").iter().any(|&c| c > 0));
    }
}

#[test]
fn emulated_cuda_small() {
    run("small.safetensors", Build::Plain, GradMode::Official);
}

#[test]
fn emulated_cuda_medium() {
    run("medium.safetensors", Build::Plain, GradMode::Official);
}

/// GradMode::Exact (true derivative incl. feature, alpha and depth images) against the CPU path.
#[test]
fn emulated_cuda_small_exact() {
    run("small.safetensors", Build::Plain, GradMode::Exact);
}

/// The medium fixture again with FMA contraction (see [`Build::Fma`]).
#[test]
fn emulated_cuda_medium_fma_contracted() {
    run("medium.safetensors", Build::Fma, GradMode::Official);
}

#[test]
fn emulated_cuda_synthetic_clamped_jacobian() {
    run_synthetic(false);
}

#[test]
fn emulated_cuda_synthetic_nothing_visible() {
    run_synthetic(true);
}
