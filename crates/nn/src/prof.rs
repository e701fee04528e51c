//! Opt-in wall-clock totals per module type, for finding hot spots in release runs
//! (`MVSPLAT360_PROFILE=1`; off by default, then a scope costs one atomic load). The one profiler of the model
//! crates: the refiner times module scopes ([`scope`]), the encoder consecutive stages ([`lap`]); `bench scene`
//! reports both.
//! Times are inclusive: a scope nested in another is counted in both. On a GPU, kernels run after their launch
//! returns: `sync_with` the device, and every scope waits for it at both ends, so a scope's time is its kernels'.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::Mutex;
use std::time::Instant;

static STATE: AtomicU8 = AtomicU8::new(0); // 0 unknown, 1 off, 2 on
static TOTALS: Mutex<BTreeMap<&'static str, (f64, u64)>> = Mutex::new(BTreeMap::new());
static SYNC: Mutex<Option<candle_core::Device>> = Mutex::new(None);

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

/// Whether profiling is on (the environment variable, or `set_enabled`).
pub fn is_enabled() -> bool {
    enabled()
}

/// Scopes wait for `dev`'s queued work at both ends (while profiling is on); a CPU device clears it.
pub fn sync_with(dev: &candle_core::Device) {
    if let Ok(mut d) = SYNC.lock() {
        *d = (!dev.is_cpu()).then(|| dev.clone());
    }
}

fn sync() {
    if let Some(d) = SYNC.lock().ok().and_then(|d| d.clone()) {
        // A failed wait shows up at the next real operation on the device; timing must not fail the run.
        let _ = d.synchronize();
    }
}

/// Time the enclosing block under `name` (when profiling is on).
pub fn scope(name: &'static str) -> Option<Scope> {
    enabled().then(|| {
        sync();
        Scope { name, start: Instant::now() }
    })
}

impl Drop for Scope {
    fn drop(&mut self) {
        sync();
        add(self.name, self.start.elapsed().as_secs_f64() * 1e3);
    }
}

fn add(name: &'static str, ms: f64) {
    if let Ok(mut t) = TOTALS.lock() {
        let e = t.entry(name).or_insert((0.0, 0));
        e.0 += ms;
        e.1 += 1;
    }
}

/// Count the time since `*t` under `name` and restart `*t` (when profiling is on): a stage of a sequence.
pub fn lap(name: &'static str, t: &mut Instant) {
    if enabled() {
        sync();
        add(name, t.elapsed().as_secs_f64() * 1e3);
        *t = Instant::now();
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
