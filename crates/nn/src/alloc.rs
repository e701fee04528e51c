//! A global allocator that keeps a few recently freed large blocks for reuse. glibc serves every allocation
//! above 32 MiB (its highest mmap threshold) with a fresh mapping and unmaps it on free, so each such buffer —
//! VGGT-1B allocates ≈ 250 MB of them per block, 72 blocks per forward — is paid again in page faults and the
//! kernel's zeroing of every page (≈ 4 % of a CPU forward). Blocks of at least [`MIN_BLOCK`] bytes are kept on
//! free (at most [`SLOTS`] of them and [`MAX_BYTES`] in all; the oldest is returned to the system first) and
//! handed out again for a request of exactly the same size and alignment, the pattern of a model's repeated
//! layers. Everything else goes to the system allocator unchanged.
//!
//! A zeroed request served from the cache is zeroed with `write_bytes` (the pages are already mapped, so that is
//! cheaper than the faults it replaces). Memory cost: up to `MAX_BYTES` of freed blocks stay resident while they
//! are being reused.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

/// Smallest block kept (below it glibc's own free lists serve reuse).
pub const MIN_BLOCK: usize = 8 << 20;
/// Blocks kept at most.
pub const SLOTS: usize = 12;
/// Bytes kept at most.
pub const MAX_BYTES: usize = 384 << 20;
/// A kept block not asked for again within this many large requests (allocations and frees of at least
/// `MIN_BLOCK`) is given back. VGGT's transformer block makes about 18.
pub const AGE_LIMIT: u64 = 64;

#[derive(Clone, Copy)]
struct Block {
    ptr: usize,
    size: usize,
    align: usize,
    /// Insertion order, for evicting the oldest.
    age: u64,
}

struct Cache {
    blocks: [Option<Block>; SLOTS],
    bytes: usize,
    clock: u64,
}

/// The caching allocator; install with `#[global_allocator] static A: LargeBlockCache = LargeBlockCache::new();`.
pub struct LargeBlockCache {
    cache: Mutex<Cache>,
    hits: AtomicUsize,
}

impl LargeBlockCache {
    pub const fn new() -> Self {
        Self { cache: Mutex::new(Cache { blocks: [None; SLOTS], bytes: 0, clock: 0 }), hits: AtomicUsize::new(0) }
    }

    /// Requests served from the cache so far.
    pub fn hits(&self) -> usize {
        self.hits.load(Ordering::Relaxed)
    }

    /// Runs `f` on the cache under the lock, then gives the blocks it evicted back to the system (outside the
    /// lock). A poisoned lock (nothing in here panics) leaves the cache out: `f` does not run.
    fn with_cache<R>(&self, f: impl FnOnce(&mut Cache, &mut Evicted) -> R) -> Option<R> {
        let mut ev = Evicted { blocks: [None; SLOTS + 1], n: 0 };
        let r = {
            let mut c = self.cache.lock().ok()?;
            c.clock += 1;
            // Blocks not asked for again within AGE_LIMIT large requests belong to another phase of the run
            // (the heads after the trunk): give them back rather than hold them at the next peak.
            let stale = c.clock.saturating_sub(AGE_LIMIT);
            for i in 0..SLOTS {
                if c.blocks[i].is_some_and(|b| b.age < stale) {
                    let b = c.blocks[i].take().expect("an occupied slot");
                    c.bytes -= b.size;
                    ev.push(b);
                }
            }
            f(&mut c, &mut ev)
        };
        for b in ev.blocks.into_iter().flatten() {
            // SAFETY: a block the system allocator gave out with exactly this layout, now held by nobody.
            unsafe { System.dealloc(b.ptr as *mut u8, Layout::from_size_align_unchecked(b.size, b.align)) };
        }
        Some(r)
    }

    fn take(&self, layout: Layout) -> Option<*mut u8> {
        let p = self.with_cache(|c, _| {
            let i = c.blocks.iter().position(|b| b.is_some_and(|b| b.size == layout.size() && b.align == layout.align()))?;
            let b = c.blocks[i].take()?;
            c.bytes -= b.size;
            Some(b.ptr as *mut u8)
        })??;
        self.hits.fetch_add(1, Ordering::Relaxed);
        Some(p)
    }

    /// Keeps the block (evicting the oldest while over the limits); false: the caller gives it back.
    fn keep(&self, ptr: *mut u8, layout: Layout) -> bool {
        if layout.size() > MAX_BYTES {
            return false;
        }
        self.with_cache(|c, ev| {
            while c.bytes + layout.size() > MAX_BYTES || c.blocks.iter().all(|b| b.is_some()) {
                let Some(i) = c.blocks.iter().enumerate().filter_map(|(i, b)| b.map(|b| (i, b.age))).min_by_key(|&(_, a)| a).map(|(i, _)| i) else {
                    return false;
                };
                let b = c.blocks[i].take().expect("an occupied slot");
                c.bytes -= b.size;
                ev.push(b);
            }
            let age = c.clock;
            let slot = c.blocks.iter_mut().find(|b| b.is_none()).expect("a free slot after eviction");
            *slot = Some(Block { ptr: ptr as usize, size: layout.size(), align: layout.align(), age });
            c.bytes += layout.size();
            true
        })
        .unwrap_or(false)
    }
}

struct Evicted {
    blocks: [Option<Block>; SLOTS + 1],
    n: usize,
}

impl Evicted {
    fn push(&mut self, b: Block) {
        self.blocks[self.n] = Some(b);
        self.n += 1;
    }
}

impl Default for LargeBlockCache {
    fn default() -> Self {
        Self::new()
    }
}

// SAFETY: every pointer handed out is either the system allocator's for this exact layout or a block of
// exactly this size and alignment that the system allocator gave out earlier and nobody else holds (it was
// freed to us and is removed from the cache under the lock before being returned).
unsafe impl GlobalAlloc for LargeBlockCache {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if layout.size() >= MIN_BLOCK {
            if let Some(p) = self.take(layout) {
                return p;
            }
        }
        System.alloc(layout)
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if layout.size() >= MIN_BLOCK {
            if let Some(p) = self.take(layout) {
                std::ptr::write_bytes(p, 0, layout.size());
                return p;
            }
        }
        System.alloc_zeroed(layout)
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        if layout.size() < MIN_BLOCK || !self.keep(ptr, layout) {
            System.dealloc(ptr, layout);
        }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // The system's realloc (mremap for large blocks) unless a cached block of the new size can be used.
        if new_size >= MIN_BLOCK {
            let new_layout = Layout::from_size_align_unchecked(new_size, layout.align());
            if let Some(p) = self.take(new_layout) {
                std::ptr::copy_nonoverlapping(ptr, p, layout.size().min(new_size));
                self.dealloc(ptr, layout);
                return p;
            }
        }
        System.realloc(ptr, layout, new_size)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Reuse of an exactly matching block, zeroing of a reused zeroed request, the limits, eviction order and
    /// aging, and realloc keeping the contents — on a private instance (not installed globally).
    #[test]
    fn keeps_and_reuses_large_blocks() {
        let a = LargeBlockCache::new();
        let l = Layout::from_size_align(MIN_BLOCK, 64).unwrap();
        unsafe {
            let p = a.alloc(l);
            assert!(!p.is_null());
            p.write_bytes(7, l.size());
            a.dealloc(p, l);
            let q = a.alloc_zeroed(l);
            assert_eq!(q, p, "the freed block is reused");
            assert_eq!(a.hits(), 1);
            let s = std::slice::from_raw_parts(q, l.size());
            assert!(s.iter().all(|&b| b == 0), "a reused zeroed request is zeroed");
            // Another size or alignment is not served from the cache.
            a.dealloc(q, l);
            let l2 = Layout::from_size_align(MIN_BLOCK + 4096, 64).unwrap();
            let r = a.alloc(l2);
            assert_ne!(r, q);
            let l3 = Layout::from_size_align(MIN_BLOCK, 128).unwrap();
            let r3 = a.alloc(l3);
            assert_ne!(r3, q);
            assert_eq!(a.hits(), 1);
            // realloc into a cached block of the new size keeps the contents.
            r.write_bytes(3, l2.size());
            let r2 = a.realloc(r, l2, MIN_BLOCK);
            assert_eq!(r2, q, "realloc takes the cached block of its new size");
            assert!(std::slice::from_raw_parts(r2, MIN_BLOCK).iter().all(|&b| b == 3));
            a.dealloc(r2, l);
            a.dealloc(r3, l3);
            // Limits: SLOTS + 2 distinct sizes freed → at most SLOTS kept, within MAX_BYTES, the oldest evicted.
            let layouts: Vec<Layout> = (0..SLOTS + 2).map(|i| Layout::from_size_align(MIN_BLOCK + 4096 * (i + 2), 64).unwrap()).collect();
            let ptrs: Vec<*mut u8> = layouts.iter().map(|&l| a.alloc(l)).collect();
            for (p, l) in ptrs.iter().zip(&layouts) {
                a.dealloc(*p, *l);
            }
            let c = a.cache.lock().unwrap();
            let kept: Vec<usize> = c.blocks.iter().flatten().map(|b| b.size).collect();
            assert!(kept.len() <= SLOTS && c.bytes <= MAX_BYTES && c.bytes == kept.iter().sum::<usize>());
            assert!(kept.contains(&layouts.last().unwrap().size()), "the newest block is kept");
            assert!(!kept.contains(&layouts[0].size()), "the oldest block was evicted");
            drop(c);
            // Aging: a kept block not asked for within AGE_LIMIT large requests is given back.
            let kept_one = layouts.last().unwrap().size();
            let other = Layout::from_size_align(MIN_BLOCK + 1, 64).unwrap();
            for _ in 0..AGE_LIMIT {
                let p = a.alloc(other);
                a.dealloc(p, other);
            }
            assert!(a.cache.lock().unwrap().blocks.iter().flatten().all(|b| b.size != kept_one), "a stale block is given back");
            assert!(a.cache.lock().unwrap().blocks.iter().flatten().any(|b| b.size == other.size()), "the block in use stays");
            // A block larger than MAX_BYTES is never kept.
            let big = Layout::from_size_align(MAX_BYTES + 4096, 64).unwrap();
            let p = a.alloc(big);
            a.dealloc(p, big);
            assert!(a.cache.lock().unwrap().blocks.iter().flatten().all(|b| b.size != big.size()));
        }
    }
}
