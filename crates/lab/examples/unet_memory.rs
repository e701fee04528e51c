//! What is alive at the peak of one guided VideoUNet step (random weights): a counting allocator keeps every
//! allocation of ≥ 8 MiB with its call stack and snapshots them whenever the live total reaches a new high.
//!
//!     cargo run --release -p mvsplat360-lab --example unet_memory -- [f32|bf16] [FRAMES] [LATENT_H] [LATENT_W]
//!
//! Prints the weights' total, the peak, and the large allocations alive at the peak grouped by the first
//! frames of this project in their stacks.

use std::alloc::{GlobalAlloc, Layout, System};
use std::backtrace::Backtrace;
use std::cell::Cell;
use std::collections::HashMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use candle_core::{DType, Device};
use mvsplat360_refiner::refiner::seeded_noise;
use mvsplat360_refiner::sampling::{guided_unet_input, v_scaling_edm};
use mvsplat360_refiner::unet::util::timestep_embedding;
use mvsplat360_refiner::unet::{UNetInputs, VideoUNet, VideoUNetConfig};

const BIG: usize = 8 << 20;

struct Counting;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);
static SNAP_AT: AtomicUsize = AtomicUsize::new(0);
type Big = HashMap<usize, (usize, Arc<Backtrace>)>;
static BIG_LIVE: Mutex<Option<Big>> = Mutex::new(None);
static SNAPSHOT: Mutex<Vec<(usize, Arc<Backtrace>)>> = Mutex::new(Vec::new());

thread_local! {
    static INSIDE: Cell<bool> = const { Cell::new(false) };
}

fn guarded(f: impl FnOnce()) {
    INSIDE.with(|i| {
        if !i.get() {
            i.set(true);
            f();
            i.set(false);
        }
    });
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(l) };
        if !p.is_null() {
            let live = LIVE.fetch_add(l.size(), Ordering::Relaxed) + l.size();
            PEAK.fetch_max(live, Ordering::Relaxed);
            if l.size() >= BIG {
                guarded(|| {
                    let bt = Arc::new(Backtrace::force_capture());
                    if let Ok(mut m) = BIG_LIVE.lock() {
                        m.get_or_insert_with(HashMap::new).insert(p as usize, (l.size(), bt));
                    }
                });
            }
            // A new high (by ≥ 4 MiB since the last snapshot): keep what is alive now.
            if live > SNAP_AT.load(Ordering::Relaxed) + (4 << 20) {
                guarded(|| {
                    SNAP_AT.store(live, Ordering::Relaxed);
                    let v: Vec<_> = BIG_LIVE.lock().ok().and_then(|m| m.as_ref().map(|m| m.values().cloned().collect())).unwrap_or_default();
                    if let Ok(mut s) = SNAPSHOT.lock() {
                        *s = v;
                    }
                });
            }
        }
        p
    }

    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        unsafe { System.dealloc(p, l) };
        LIVE.fetch_sub(l.size(), Ordering::Relaxed);
        if l.size() >= BIG {
            guarded(|| {
                if let Ok(mut m) = BIG_LIVE.lock() {
                    if let Some(m) = m.as_mut() {
                        m.remove(&(p as usize));
                    }
                }
            });
        }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn mib(b: usize) -> f64 {
    b as f64 / (1 << 20) as f64
}

/// The innermost frames of this project in a stack (skipping the allocator and candle's storage plumbing).
fn site(bt: &Backtrace) -> String {
    let s = bt.to_string();
    let mut out = Vec::new();
    for line in s.lines() {
        let t = line.trim();
        if let Some(name) = t.split_once(": ").map(|x| x.1) {
            if name.starts_with("mvsplat360") && !name.contains("unet_memory") {
                let short: String = name.split("::").filter(|p| !p.starts_with('h') || p.len() != 17).collect::<Vec<_>>().join("::");
                out.push(short);
                if out.len() == 3 {
                    break;
                }
            }
        }
    }
    out.join(" < ")
}

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    let dtype = match a.get(1).map(String::as_str) {
        Some("bf16") => DType::BF16,
        _ => DType::F32,
    };
    let num = |i: usize, d: usize| a.get(i).and_then(|s| s.parse().ok()).unwrap_or(d);
    let (n, lh, lw) = (num(2, 14), num(3, 64), num(4, 112));
    let dev = Device::Cpu;
    let cfg = VideoUNetConfig::default();
    let unet = VideoUNet::random_as(&cfg, 0, &dev, dtype)?;
    let weights = LIVE.load(Ordering::Relaxed);
    PEAK.store(weights, Ordering::Relaxed);
    SNAP_AT.store(weights, Ordering::Relaxed);
    let x = seeded_noise(1, &[n, 4, lh, lw], &dev)?;
    let concat = seeded_noise(2, &[n, cfg.in_channels.saturating_sub(4), lh, lw], &dev)?;
    let ctx = seeded_noise(3, &[2 * n, 1, cfg.context_dim], &dev)?;
    let (_, _, c_in, c_noise) = v_scaling_edm(700.0);
    let y = match cfg.adm_in_channels {
        Some(adm) => Some(timestep_embedding(&vec![0.02; 2 * n], adm, 10000.0, &dev)?),
        None => None,
    };
    let inp = guided_unet_input(&x, &concat, c_in)?;
    let t = std::time::Instant::now();
    let v = unet.forward(&UNetInputs { x: &inp, timesteps: &vec![c_noise; 2 * n], context: &ctx, y: y.as_ref(), num_video_frames: n, num_splits: None })?;
    let _ = v.sum_all()?.to_scalar::<f32>()?;
    let peak = PEAK.load(Ordering::Relaxed);
    println!(
        "{dtype:?} 2x{n} frames {lh}x{lw}: step {:.1} s; weights {:.0} MiB, peak {:.0} MiB (activations {:.0} MiB)",
        t.elapsed().as_secs_f64(),
        mib(weights),
        mib(peak),
        mib(peak - weights)
    );
    let snap = SNAPSHOT.lock().map(|s| s.clone()).unwrap_or_default();
    let mut by: HashMap<String, (usize, usize)> = HashMap::new();
    for (size, bt) in &snap {
        let e = by.entry(site(bt)).or_default();
        e.0 += size;
        e.1 += 1;
    }
    let mut rows: Vec<_> = by.into_iter().collect();
    rows.sort_by(|a, b| b.1 .0.cmp(&a.1 .0));
    let total: usize = rows.iter().map(|r| r.1 .0).sum();
    println!("alive at the peak, allocations ≥ {} MiB: {:.0} MiB", BIG >> 20, mib(total));
    for (s, (b, c)) in rows {
        println!("{:>8.0} MiB {c:>4}×  {s}", mib(b));
    }
    Ok(())
}
