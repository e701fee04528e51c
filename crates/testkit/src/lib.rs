//! Test-only helpers shared by the parity tests of every model crate.
//!
//! Fixtures live in `$MVSPLAT360_FIXTURES`, default `<repo root>/../shared/fixtures`.
//! A missing folder is a test failure with a message saying where we looked, never a silent pass.

pub mod hub_standin;
pub mod mutate;

use std::collections::HashMap;
use std::path::PathBuf;

use candle_core::{DType, Device, Tensor};

/// Repository root, found from this crate's manifest directory (`<root>/crates/testkit`).
pub fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).parent().and_then(|p| p.parent()).map(PathBuf::from).expect("testkit lives at <root>/crates/testkit")
}

/// The golden-fixture folder; panics (failing the test) with the searched path when absent.
pub fn fixtures_dir() -> PathBuf {
    let dir = match std::env::var_os("MVSPLAT360_FIXTURES") {
        Some(p) => {
            let p = PathBuf::from(p);
            if p.is_absolute() {
                p
            } else {
                repo_root().join(p)
            }
        }
        None => repo_root().join("../shared/fixtures"),
    };
    assert!(dir.is_dir(), "golden fixtures not found at {} (set MVSPLAT360_FIXTURES to the folder holding encoder/, rasterizer/, svd/)", dir.display());
    dir
}

/// One fixture file, e.g. `fixture("rasterizer/small.safetensors")`; fails the test if missing.
pub fn fixture(rel: &str) -> PathBuf {
    let p = fixtures_dir().join(rel);
    assert!(p.is_file(), "fixture file missing: {}", p.display());
    p
}

/// Load every tensor of a safetensors fixture on the CPU.
pub fn load(rel: &str) -> HashMap<String, Tensor> {
    let p = fixture(rel);
    candle_core::safetensors::load(&p, &Device::Cpu).unwrap_or_else(|e| panic!("cannot read {}: {e}", p.display()))
}

/// Fetch a named tensor from a loaded fixture, failing with the name if absent.
pub fn get<'a>(map: &'a HashMap<String, Tensor>, name: &str) -> &'a Tensor {
    map.get(name).unwrap_or_else(|| panic!("fixture has no tensor `{name}`"))
}

/// Max |a-b| and max |ref| over two tensors of the same shape (compared in f64).
pub fn max_abs_diff(actual: &Tensor, expected: &Tensor) -> (f64, f64) {
    assert_eq!(actual.dims(), expected.dims(), "shape mismatch");
    let a = actual.to_dtype(DType::F64).unwrap().flatten_all().unwrap().to_vec1::<f64>().unwrap();
    let e = expected.to_dtype(DType::F64).unwrap().flatten_all().unwrap().to_vec1::<f64>().unwrap();
    let mut diff = 0f64;
    let mut maxref = 0f64;
    for (x, y) in a.iter().zip(e.iter()) {
        assert!(x.is_finite(), "non-finite value in actual tensor");
        diff = diff.max((x - y).abs());
        maxref = maxref.max(y.abs());
    }
    (diff, maxref)
}

/// Assert max |a-b| <= tol.
pub fn assert_close(name: &str, actual: &Tensor, expected: &Tensor, tol: f64) {
    let (d, m) = max_abs_diff(actual, expected);
    assert!(d <= tol, "{name}: max abs diff {d:.3e} > tol {tol:.1e} (max |ref| {m:.3e})");
}

/// Assert max |a-b| / max(1, max|ref|) <= tol (the fixtures' normalised error).
pub fn assert_close_norm(name: &str, actual: &Tensor, expected: &Tensor, tol: f64) {
    let (d, m) = max_abs_diff(actual, expected);
    let e = d / m.max(1.0);
    assert!(e <= tol, "{name}: normalised error {e:.3e} > tol {tol:.1e} (max abs diff {d:.3e}, max |ref| {m:.3e})");
}

/// Assert max |a-b| <= tol * max|ref| (relative to the tensor's largest magnitude).
pub fn assert_close_rel_max(name: &str, actual: &Tensor, expected: &Tensor, tol: f64) {
    let (d, m) = max_abs_diff(actual, expected);
    assert!(d <= tol * m.max(f64::MIN_POSITIVE), "{name}: max abs diff {d:.3e} > {tol:.1e} x max|ref| {m:.3e}");
}

/// Element-wise comparison of `actual` against `expected` with |a − e| ≤ atol + rtol·|e| per entry.
#[derive(Debug, Clone, Copy)]
pub struct Spread {
    /// Entries compared.
    pub n: usize,
    /// max |a − e|.
    pub max_abs: f64,
    /// max |a − e| / |e| over the entries with |e| > 0 (the f32 noise relative to each value).
    pub max_rel: f64,
    /// max |a − e| / (atol + rtol·|e|): ≤ 1 passes; the headroom left by the tolerance.
    pub worst_ratio: f64,
    /// Index, actual and expected value of the entry with the largest ratio.
    pub worst: (usize, f64, f64),
    /// Entries over the tolerance.
    pub n_bad: usize,
    /// max |e|.
    pub max_ref: f64,
    /// Smallest rtol that passes with this atol, and smallest atol that passes with this rtol.
    pub rtol_needed: f64,
    pub atol_needed: f64,
}

/// [`Spread`] of two equally long slices (compared in f64). Panics on a length mismatch or a non-finite
/// `actual` entry whose reference is finite.
pub fn spread(actual: &[f64], expected: &[f64], atol: f64, rtol: f64) -> Spread {
    assert_eq!(actual.len(), expected.len(), "length mismatch");
    let mut s = Spread {
        n: actual.len(),
        max_abs: 0.0,
        max_rel: 0.0,
        worst_ratio: 0.0,
        worst: (0, 0.0, 0.0),
        n_bad: 0,
        max_ref: 0.0,
        rtol_needed: 0.0,
        atol_needed: 0.0,
    };
    for (i, (&a, &e)) in actual.iter().zip(expected).enumerate() {
        assert!(a.is_finite() || !e.is_finite(), "entry {i}: actual {a} is not finite (expected {e})");
        let d = (a - e).abs();
        let tol = atol + rtol * e.abs();
        let ratio = if tol > 0.0 {
            d / tol
        } else if d == 0.0 {
            0.0
        } else {
            f64::INFINITY
        };
        s.max_abs = s.max_abs.max(d);
        s.max_ref = s.max_ref.max(e.abs());
        s.atol_needed = s.atol_needed.max(d - rtol * e.abs());
        if d > atol {
            s.rtol_needed = s.rtol_needed.max(if e != 0.0 { (d - atol) / e.abs() } else { f64::INFINITY });
        }
        if e != 0.0 {
            s.max_rel = s.max_rel.max(d / e.abs());
        }
        if ratio > 1.0 || ratio.is_nan() {
            s.n_bad += 1;
        }
        if ratio > s.worst_ratio || (i == 0 && ratio.is_nan()) {
            s.worst_ratio = ratio;
            s.worst = (i, a, e);
        }
    }
    s
}

/// Compare every entry with |a − e| ≤ atol + rtol·|e| (numpy's `allclose` rule), print the spread so a
/// tolerance can be justified from the log, and return the failure message, if any. An all-zero reference
/// fails (the check would be vacuous).
pub fn allclose_report(name: &str, actual: &[f64], expected: &[f64], atol: f64, rtol: f64) -> Option<String> {
    let s = spread(actual, expected, atol, rtol);
    eprintln!(
        "{name}: n {}, max abs {:.3e}, max rel {:.3e}, max|ref| {:.3e}; worst {:.3} of tol (atol {atol:.1e}, rtol {rtol:.1e}) at [{}] {:.6e} vs {:.6e}; passes with rtol >= {:.2e} at this atol, atol >= {:.2e} at this rtol",
        s.n, s.max_abs, s.max_rel, s.max_ref, s.worst_ratio, s.worst.0, s.worst.1, s.worst.2, s.rtol_needed, s.atol_needed.max(0.0)
    );
    if s.max_ref == 0.0 && s.n > 0 {
        return Some(format!("{name}: reference is all zeros"));
    }
    (s.n_bad > 0).then(|| {
        format!(
            "{name}: {} of {} entries exceed |a-e| <= {atol:.1e} + {rtol:.1e}|e| (worst: [{}] {:.6e} vs {:.6e}, {:.2}x tol; max abs {:.3e})",
            s.n_bad, s.n, s.worst.0, s.worst.1, s.worst.2, s.worst_ratio, s.max_abs
        )
    })
}

/// Assert [`allclose_report`] finds no failure.
pub fn assert_allclose_slice(name: &str, actual: &[f64], expected: &[f64], atol: f64, rtol: f64) {
    if let Some(msg) = allclose_report(name, actual, expected, atol, rtol) {
        panic!("{msg}");
    }
}

/// A tensor's values in f64, row-major.
pub fn to_f64(t: &Tensor) -> Vec<f64> {
    t.contiguous().unwrap().to_dtype(DType::F64).unwrap().flatten_all().unwrap().to_vec1::<f64>().unwrap()
}

/// [`allclose_report`] for two tensors of the same shape.
pub fn allclose(name: &str, actual: &Tensor, expected: &Tensor, atol: f64, rtol: f64) -> Option<String> {
    assert_eq!(actual.dims(), expected.dims(), "{name}: shape mismatch");
    allclose_report(name, &to_f64(actual), &to_f64(expected), atol, rtol)
}

/// [`assert_allclose_slice`] for two tensors of the same shape.
pub fn assert_allclose(name: &str, actual: &Tensor, expected: &Tensor, atol: f64, rtol: f64) {
    if let Some(msg) = allclose(name, actual, expected, atol, rtol) {
        panic!("{msg}");
    }
}

/// Panics listing every failure collected by [`allclose`] / [`allclose_report`] (so one run reports them all).
pub fn assert_no_failures(what: &str, failures: &[String]) {
    assert!(failures.is_empty(), "{what}: {} check(s) failed:\n{}", failures.len(), failures.join("\n"));
}

/// The official SH mask of degree l (`gaussian_adapter.sh_mask`): 1, then 0.1·0.25^l — the scale of that degree's
/// coefficients, by which SH tolerances are scaled.
pub fn sh_mask(l: usize) -> f64 {
    if l == 0 {
        1.0
    } else {
        0.1 * 0.25f64.powi(l as i32)
    }
}

/// The slice of coefficients of SH degree `l` along the last dimension (k = l² .. (l+1)²).
pub fn sh_degree_block(t: &Tensor, l: usize) -> Tensor {
    let last = t.rank() - 1;
    t.narrow(last, l * l, 2 * l + 1).unwrap()
}

/// Error model of a parity check against a float32 reference: entry i passes when
///
/// |a_i − e_i| ≤ abs + rel·|e_i| + of_scale·S_i,
///
/// S_i = the reference's scale around entry i: max |e| (or the RMS of e, with `rms`) over the group of `group`
/// consecutive entries that holds i (`group` 0 = the whole tensor; e.g. 9 = one 3×3 covariance).
///
/// Why a scale term: two float32 implementations of the same network round differently, and an output that is
/// a sum of terms of the tensor's size carries an absolute error of about u·(size of the terms) even when the
/// sum itself is near zero (cancellation). An element-wise rtol alone fails on such entries by noise, and an
/// atol alone cannot follow the tensor's magnitude across seeds and sizes; `of_scale` × the reference's own
/// scale does both.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tol {
    pub abs: f64,
    pub rel: f64,
    pub of_scale: f64,
    pub group: usize,
    pub rms: bool,
}

impl Tol {
    /// f × max |ref| of the whole tensor.
    pub const fn of_max(f: f64) -> Self {
        Tol { abs: 0.0, rel: 0.0, of_scale: f, group: 0, rms: false }
    }
    /// f × RMS of the whole reference.
    pub const fn of_rms(f: f64) -> Self {
        Tol { abs: 0.0, rel: 0.0, of_scale: f, group: 0, rms: true }
    }
    /// f × max |ref| over each group of `group` consecutive entries (per Gaussian, per pixel, ...).
    pub const fn of_group_max(f: f64, group: usize) -> Self {
        Tol { abs: 0.0, rel: 0.0, of_scale: f, group, rms: false }
    }
    /// Element-wise relative bound only.
    pub const fn rel(r: f64) -> Self {
        Tol { abs: 0.0, rel: r, of_scale: 0.0, group: 0, rms: false }
    }
    /// Absolute bound only.
    pub const fn abs(a: f64) -> Self {
        Tol { abs: a, rel: 0.0, of_scale: 0.0, group: 0, rms: false }
    }
    pub const fn plus_rel(self, r: f64) -> Self {
        Tol { rel: r, ..self }
    }
    pub const fn plus_abs(self, a: f64) -> Self {
        Tol { abs: a, ..self }
    }
    /// The same model with every term multiplied by `k` (e.g. an SH degree's mask).
    pub fn times(self, k: f64) -> Self {
        Tol { abs: self.abs * k, of_scale: self.of_scale * k, ..self }
    }

    /// The bound of every entry of `expected`.
    pub fn bounds(&self, expected: &[f64]) -> Vec<f64> {
        let n = expected.len();
        let g = if self.group == 0 { n.max(1) } else { self.group };
        assert!(n % g == 0, "group of {g} entries does not divide {n}");
        let mut out = Vec::with_capacity(n);
        for chunk in expected.chunks(g) {
            let s = if self.of_scale == 0.0 {
                0.0
            } else if self.rms {
                (chunk.iter().map(|x| x * x).sum::<f64>() / chunk.len() as f64).sqrt()
            } else {
                chunk.iter().fold(0f64, |m, x| m.max(x.abs()))
            };
            out.extend(chunk.iter().map(|e| self.abs + self.rel * e.abs() + self.of_scale * s));
        }
        out
    }
}

/// `actual` with 1 % of its entries (at least one; every 100th, from index 37 % n) moved by `factor` × their
/// bound, away from the reference. A check whose bounds are those `bounds` must fail on the result.
pub fn perturb_one_percent(actual: &[f64], expected: &[f64], bounds: &[f64], factor: f64) -> Vec<f64> {
    let mut out = actual.to_vec();
    let n = out.len();
    if n == 0 {
        return out;
    }
    let mut i = 37 % n;
    loop {
        let dir = if actual[i] >= expected[i] { 1.0 } else { -1.0 };
        out[i] += dir * factor * bounds[i];
        i += 100;
        if i >= n {
            break;
        }
    }
    out
}

/// Entries over their bound, the worst ratio |a − e| / bound and its index.
fn over_bounds(actual: &[f64], expected: &[f64], bounds: &[f64]) -> (usize, f64, usize) {
    let mut n_bad = 0;
    let (mut worst, mut at) = (0f64, 0usize);
    for (i, ((a, e), b)) in actual.iter().zip(expected).zip(bounds).enumerate() {
        let d = (a - e).abs();
        let r = if *b > 0.0 {
            d / b
        } else if d == 0.0 {
            0.0
        } else {
            f64::INFINITY
        };
        if !(r <= 1.0) {
            n_bad += 1;
        }
        if r > worst || r.is_nan() {
            worst = r;
            at = i;
        }
    }
    (n_bad, worst, at)
}

/// Compare every entry against its own bound (see [`Tol`]), print the spread (max |Δ|, the reference's max and
/// RMS, the worst fraction of the bound used), and return the failure message, if any. Also proves the check is
/// not vacuous: moving 1 % of `actual`'s entries by 3× their bound must fail it, and an all-zero reference fails.
pub fn check_bounds(name: &str, actual: &[f64], expected: &[f64], bounds: &[f64]) -> Option<String> {
    assert_eq!(actual.len(), expected.len(), "{name}: length mismatch");
    assert_eq!(bounds.len(), expected.len(), "{name}: bounds length mismatch");
    for (i, (a, e)) in actual.iter().zip(expected).enumerate() {
        assert!(a.is_finite() || !e.is_finite(), "{name}: entry {i}: actual {a} is not finite (expected {e})");
    }
    let n = expected.len();
    let max_ref = expected.iter().fold(0f64, |m, x| m.max(x.abs()));
    let rms_ref = (expected.iter().map(|x| x * x).sum::<f64>() / n.max(1) as f64).sqrt();
    let max_abs = actual.iter().zip(expected).fold(0f64, |m, (a, e)| m.max((a - e).abs()));
    let (n_bad, worst, at) = over_bounds(actual, expected, bounds);
    eprintln!(
        "{name}: n {n}, max abs {max_abs:.3e}, max|ref| {max_ref:.3e}, rms ref {rms_ref:.3e}, max abs/max|ref| {:.3e}; worst {worst:.3} of bound at [{at}] {:.6e} vs {:.6e} (bound {:.3e})",
        max_abs / max_ref.max(f64::MIN_POSITIVE),
        actual.get(at).copied().unwrap_or(0.0),
        expected.get(at).copied().unwrap_or(0.0),
        bounds.get(at).copied().unwrap_or(0.0),
    );
    if n > 0 && max_ref == 0.0 {
        return Some(format!("{name}: reference is all zeros"));
    }
    let moved = perturb_one_percent(actual, expected, bounds, 3.0);
    let (caught, _, _) = over_bounds(&moved, expected, bounds);
    if caught == 0 || bounds.iter().any(|b| !b.is_finite()) {
        return Some(format!("{name}: the check is vacuous: moving 1 % of the entries by 3x their bound still passes"));
    }
    (n_bad > 0).then(|| {
        format!(
            "{name}: {n_bad} of {n} entries exceed their bound (worst: [{at}] {:.6e} vs {:.6e}, {worst:.2}x its bound {:.3e}; max abs {max_abs:.3e}, max|ref| {max_ref:.3e})",
            actual[at], expected[at], bounds[at]
        )
    })
}

/// [`check_bounds`] with the bounds of a [`Tol`] model.
pub fn check_slice(name: &str, actual: &[f64], expected: &[f64], tol: Tol) -> Option<String> {
    check_bounds(name, actual, expected, &tol.bounds(expected))
}

/// [`check_slice`] for two tensors of the same shape.
pub fn check(name: &str, actual: &Tensor, expected: &Tensor, tol: Tol) -> Option<String> {
    assert_eq!(actual.dims(), expected.dims(), "{name}: shape mismatch");
    check_slice(name, &to_f64(actual), &to_f64(expected), tol)
}

/// Panics with the message of [`check`], if any.
pub fn assert_check(name: &str, actual: &Tensor, expected: &Tensor, tol: Tol) {
    if let Some(msg) = check(name, actual, expected, tol) {
        panic!("{msg}");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn allclose_rule_is_per_entry() {
        let e = [1.0, 1e-3, -200.0, 0.0];
        // Each entry just inside atol + rtol|e|.
        let a: Vec<f64> = e.iter().map(|&x: &f64| x + 0.99 * (1e-6 + 1e-4 * x.abs())).collect();
        assert_allclose_slice("inside", &a, &e, 1e-6, 1e-4);
        // An error fine for the largest value but not for a small one must fail.
        let mut b = e.to_vec();
        b[1] += 1e-4;
        let s = spread(&b, &e, 1e-6, 1e-4);
        assert_eq!(s.n_bad, 1);
        assert_eq!(s.worst.0, 1);
        assert!(std::panic::catch_unwind(|| assert_allclose_slice("outside", &b, &e, 1e-6, 1e-4)).is_err());
        assert!(std::panic::catch_unwind(|| assert_allclose_slice("zeros", &[0.0], &[0.0], 1e-6, 1e-4)).is_err());
        assert!(std::panic::catch_unwind(|| assert_allclose_slice("nan", &[f64::NAN], &[1.0], 1e-6, 1e-4)).is_err());
    }
    #[test]
    fn tol_bounds_follow_the_scale_of_each_group() {
        let e = [1.0, -4.0, 0.0, 2.0, 0.5, -0.25];
        let b = Tol::of_group_max(0.1, 3).plus_rel(0.01).plus_abs(1e-3).bounds(&e);
        let want = [1e-3 + 0.01 + 0.4, 1e-3 + 0.04 + 0.4, 1e-3 + 0.4, 1e-3 + 0.02 + 0.2, 1e-3 + 0.005 + 0.2, 1e-3 + 0.0025 + 0.2];
        for (x, y) in b.iter().zip(want) {
            assert!((x - y).abs() < 1e-12, "{b:?}");
        }
        let r = Tol::of_rms(1.0).bounds(&[3.0, -4.0]);
        assert!((r[0] - (12.5f64).sqrt()).abs() < 1e-12);
        assert_eq!(Tol::of_max(0.5).bounds(&[2.0, -8.0]), vec![4.0, 4.0]);
    }

    #[test]
    fn check_fails_when_one_percent_moves_by_three_bounds() {
        // 1000 entries of a smooth reference, the actual values inside 0.9 of the bound.
        let e: Vec<f64> = (0..1000).map(|i| (i as f64 * 0.01).sin() * 5.0).collect();
        let tol = Tol::of_max(1e-5).plus_rel(1e-4);
        let bounds = tol.bounds(&e);
        let a: Vec<f64> = e.iter().zip(&bounds).enumerate().map(|(i, (x, b))| x + if i % 2 == 0 { 0.9 } else { -0.9 } * b).collect();
        assert!(check_bounds("inside", &a, &e, &bounds).is_none());
        let moved = perturb_one_percent(&a, &e, &bounds, 3.0);
        assert_eq!(moved.iter().zip(&a).filter(|(x, y)| x != y).count(), 10);
        let msg = check_bounds("moved", &moved, &e, &bounds).expect("1 % moved by 3x the bound must fail");
        assert!(msg.contains("10 of 1000"), "{msg}");
        // A vacuous bound is reported as such; an all-zero reference fails.
        assert!(check_bounds("vacuous", &a, &e, &vec![f64::INFINITY; 1000]).unwrap().contains("vacuous"));
        assert!(check_slice("zeros", &[0.0], &[0.0], Tol::abs(1.0)).unwrap().contains("all zeros"));
        // Few entries: at least one moves.
        assert!(check_slice("tiny", &[1.0, 2.0], &[1.0, 2.0], Tol::rel(1e-6)).is_none());
        assert_eq!(perturb_one_percent(&[1.0, 2.0], &[1.0, 2.0], &[0.1, 0.1], 3.0).iter().filter(|&&x| x != 1.0 && x != 2.0).count(), 1);
    }
}
