//! Test-only helpers shared by the parity tests of every model crate.
//!
//! Fixtures live in `$MVSPLAT360_FIXTURES`, default `<repo root>/../shared/fixtures`.
//! A missing folder is a test failure with a message saying where we looked, never a silent pass.

use std::collections::HashMap;
use std::path::PathBuf;

use candle_core::{DType, Device, Tensor};

/// Repository root, found from this crate's manifest directory (`<root>/crates/testkit`).
pub fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .and_then(|p| p.parent())
        .map(PathBuf::from)
        .expect("testkit lives at <root>/crates/testkit")
}

/// The golden-fixture folder; panics (failing the test) with the searched path when absent.
pub fn fixtures_dir() -> PathBuf {
    let dir = match std::env::var_os("MVSPLAT360_FIXTURES") {
        Some(p) => {
            let p = PathBuf::from(p);
            if p.is_absolute() { p } else { repo_root().join(p) }
        }
        None => repo_root().join("../shared/fixtures"),
    };
    assert!(
        dir.is_dir(),
        "golden fixtures not found at {} (set MVSPLAT360_FIXTURES to the folder holding encoder/, rasterizer/, svd/)",
        dir.display()
    );
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
    candle_core::safetensors::load(&p, &Device::Cpu)
        .unwrap_or_else(|e| panic!("cannot read {}: {e}", p.display()))
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
