//! Process-wide setup every heavy command does once at start-up.

/// Make glibc malloc reuse freed memory instead of mapping and unmapping every large tensor buffer: candle
/// allocates a fresh `Vec` per op, and with glibc's defaults each buffer over 32 MiB is a new `mmap` whose pages
/// the kernel faults in and zeroes (≈ 25% of the encoder's forward time on 2 cores). Serving large blocks from
/// the heap and never trimming it turns that into plain reuse; peak RSS stays about the same. One arena: a
/// non-main arena cannot hold blocks over 64 MiB and maps them afresh (e.g. the rasterizer's 170 MB SH gradient
/// allocated on a worker thread). Call before any worker thread starts (no-op off glibc).
pub fn init_process() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator parameters; it runs before the heavy work starts.
    unsafe {
        libc::mallopt(libc::M_ARENA_MAX, 1);
        libc::mallopt(libc::M_MMAP_MAX, 0);
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
        libc::mallopt(libc::M_TOP_PAD, 256 << 20);
    }
}

/// Peak resident set size of this process in MiB (Linux `VmHWM`), None elsewhere.
pub fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}
