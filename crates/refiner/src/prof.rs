//! Opt-in wall-clock totals per module type, for finding hot spots in release runs
//! (`MVSPLAT360_PROFILE=1`; off by default, then a scope costs one atomic load).
//! Times are inclusive: a scope nested in another is counted in both.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::Mutex;
use std::time::Instant;

static STATE: AtomicU8 = AtomicU8::new(0); // 0 unknown, 1 off, 2 on
static TOTALS: Mutex<BTreeMap<&'static str, (f64, u64)>> = Mutex::new(BTreeMap::new());

fn enabled() -> bool {
    match STATE.load(Ordering::Relaxed) {
        1 => false,
        2 => true,
        _ => {
            let on = std::env::var("MVSPLAT360_PROFILE").is_ok_and(|v| !v.is_empty() && v != "0");
            STATE.store(if on { 2 } else { 1 }, Ordering::Relaxed);
            on
        }
    }
}

/// Force profiling on or off (overrides the environment variable).
pub fn set_enabled(on: bool) {
    STATE.store(if on { 2 } else { 1 }, Ordering::Relaxed);
}

pub struct Scope {
    name: &'static str,
    start: Instant,
}

/// Time the enclosing block under `name` (when profiling is on).
pub fn scope(name: &'static str) -> Option<Scope> {
    enabled().then(|| Scope { name, start: Instant::now() })
}

impl Drop for Scope {
    fn drop(&mut self) {
        let ms = self.start.elapsed().as_secs_f64() * 1e3;
        if let Ok(mut t) = TOTALS.lock() {
            let e = t.entry(self.name).or_insert((0.0, 0));
            e.0 += ms;
            e.1 += 1;
        }
    }
}

/// (name, total ms, calls), largest total first; clears the totals.
pub fn take_report() -> Vec<(&'static str, f64, u64)> {
    let mut v: Vec<_> = match TOTALS.lock() {
        Ok(mut t) => std::mem::take(&mut *t).into_iter().map(|(k, (ms, n))| (k, ms, n)).collect(),
        Err(_) => Vec::new(),
    };
    v.sort_by(|a, b| b.1.total_cmp(&a.1));
    v
}
