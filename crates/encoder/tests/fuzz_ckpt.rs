//! Seeded mutations of a Lightning `.ckpt` (the official-eval fixture's, 6.7 MB): the pickle or one tensor
//! entry mutated inside the zip. Opening it and loading every tensor must end in `Ok` or an error, never a panic
//! (60 cases, about 13 s: each rewrites and reads the whole 6.7 MB file).
//! `MVSPLAT360_FUZZ_SEED` / `MVSPLAT360_FUZZ_CASES` run other and longer hunts.

use std::path::Path;
use std::time::{Duration, Instant};

use candle_core::Device;
use mvsplat360_encoder::weights::Checkpoint;
use mvsplat360_testkit::mutate::{mutate_zip_entry, Rng};

fn read_all(p: &Path) -> bool {
    let Ok(w) = Checkpoint::open(p) else { return false };
    w.keys().iter().all(|k| w.load_raw(k, &Device::Cpu).is_ok())
}

#[test]
fn lightning_checkpoints() {
    let seed_file = mvsplat360_testkit::repo_root().join("crates/pipeline/tests/fixtures/official_eval/model.ckpt");
    let original = std::fs::read(&seed_file).unwrap();
    let seed: u64 = std::env::var("MVSPLAT360_FUZZ_SEED").ok().and_then(|s| s.parse().ok()).unwrap_or(20261202);
    let n: usize = std::env::var("MVSPLAT360_FUZZ_CASES").ok().and_then(|s| s.parse().ok()).unwrap_or(60);
    let mut rng = Rng(seed ^ 0x636b_7074);
    let dir = tempfile::tempdir().unwrap();
    let target = dir.path().join("model.ckpt");
    let (mut ok, mut refused, mut panics) = (0, 0, Vec::new());
    let t0 = Instant::now();
    for case in 0..n {
        std::fs::write(&target, mutate_zip_entry(&mut rng, &original, "data.pkl")).unwrap();
        let t = Instant::now();
        match std::panic::catch_unwind(|| read_all(&target)) {
            Ok(true) => ok += 1,
            Ok(false) => refused += 1,
            Err(_) => {
                std::fs::copy(&target, dir.path().join(format!("panic-{case}.ckpt"))).unwrap();
                panics.push(case);
            }
        }
        // A hang deadline, not a speed check (a case reads in milliseconds).
        assert!(t.elapsed() < Duration::from_secs(60), "case {case} took {:?}: a hang", t.elapsed());
    }
    eprintln!("model.ckpt: {n} cases ({ok} read, {refused} refused) in {:.1} s, seed {seed}", t0.elapsed().as_secs_f64());
    if !panics.is_empty() {
        let kept = dir.keep();
        panic!("{} case(s) panicked: {:?}; inputs kept in {}", panics.len(), &panics[..panics.len().min(10)], kept.display());
    }
}
