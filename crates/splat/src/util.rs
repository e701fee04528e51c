//! A shared-write view for parallel loops whose threads write disjoint indices.

#[derive(Clone, Copy)]
pub(crate) struct SharedMut<T> {
    ptr: *mut T,
    len: usize,
}

// SAFETY: every user writes disjoint indices from different threads (documented at each call site).
unsafe impl<T: Send> Send for SharedMut<T> {}
unsafe impl<T: Send> Sync for SharedMut<T> {}

impl<T> SharedMut<T> {
    pub fn new(s: &mut [T]) -> Self {
        Self { ptr: s.as_mut_ptr(), len: s.len() }
    }

    /// # Safety
    /// `ptr` must be valid for writing `len` values while the view is used.
    pub unsafe fn from_raw(ptr: *mut T, len: usize) -> Self {
        Self { ptr, len }
    }

    /// # Safety
    /// No other thread may access index `i` concurrently.
    #[inline(always)]
    pub unsafe fn write(&self, i: usize, v: T) {
        assert!(i < self.len);
        *self.ptr.add(i) = v;
    }
}

/// A few reusable large buffers: re-touching already-mapped memory is far cheaper than page-faulting fresh
/// allocations of tens of MB on every call. Holds at most `MAX_POOLED` vectors per pool.
pub(crate) struct Pool<T>(std::sync::Mutex<Vec<Vec<T>>>);

const MAX_POOLED: usize = 6;

impl<T: Clone> Pool<T> {
    pub const fn new() -> Self {
        Pool(std::sync::Mutex::new(Vec::new()))
    }

    /// A vector of length `len`; reused contents are stale (callers overwrite what they read).
    pub fn take(&self, len: usize, fill: T) -> Vec<T> {
        let mut v = self.0.lock().ok().and_then(|mut p| p.pop()).unwrap_or_default();
        v.truncate(len);
        v.resize(len, fill);
        v
    }

    pub fn put(&self, v: Vec<T>) {
        if v.capacity() == 0 {
            return;
        }
        if let Ok(mut p) = self.0.lock() {
            if p.len() < MAX_POOLED {
                p.push(v);
            }
        }
    }
}

/// A vector that returns itself to its [`Pool`] when dropped.
pub(crate) struct Pooled<T: Clone + 'static> {
    v: Vec<T>,
    pool: &'static Pool<T>,
}

impl<T: Clone + 'static> Pooled<T> {
    pub fn new(v: Vec<T>, pool: &'static Pool<T>) -> Self {
        Pooled { v, pool }
    }
}

impl<T: Clone + 'static> std::ops::Deref for Pooled<T> {
    type Target = Vec<T>;
    fn deref(&self) -> &Vec<T> {
        &self.v
    }
}

impl<T: Clone + 'static> std::ops::DerefMut for Pooled<T> {
    fn deref_mut(&mut self) -> &mut Vec<T> {
        &mut self.v
    }
}

impl<T: Clone + 'static> Drop for Pooled<T> {
    fn drop(&mut self) {
        self.pool.put(std::mem::take(&mut self.v));
    }
}

impl<T: Clone + 'static> Clone for Pooled<T> {
    fn clone(&self) -> Self {
        Pooled { v: self.v.clone(), pool: self.pool }
    }
}

impl<T: Clone + 'static> std::fmt::Debug for Pooled<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "[{} pooled values]", self.v.len())
    }
}

pub(crate) static POOL_U32: Pool<u32> = Pool::new();
pub(crate) static POOL_F32: Pool<f32> = Pool::new();
pub(crate) static POOL_U64: Pool<u64> = Pool::new();
pub(crate) static POOL_GEO: Pool<[f32; 8]> = Pool::new();
pub(crate) static POOL_REC: Pool<[u64; 2]> = Pool::new();

/// A vector of `len` values that the caller fully writes (in parallel) before reading: no zero-fill pass.
/// Large ones are advised to use transparent huge pages, since first-touching ~100-200 MB of fresh 4 KiB pages
/// (e.g. the SH gradient) costs tens of thousands of page faults.
pub(crate) struct Uninit<T> {
    v: Vec<T>,
    len: usize,
}

impl<T: Copy> Uninit<T> {
    pub fn new(len: usize) -> Self {
        let v = Vec::with_capacity(len);
        #[cfg(target_os = "linux")]
        {
            const BIG: usize = 8 << 20;
            const HUGE: usize = 2 << 20;
            let bytes = len.saturating_mul(std::mem::size_of::<T>());
            let p = v.as_ptr() as usize;
            let a0 = (p + HUGE - 1) & !(HUGE - 1);
            let a1 = (p + bytes) & !(HUGE - 1);
            if bytes >= BIG && a1 > a0 {
                // SAFETY: the range lies inside this allocation; the advice only affects how it is backed.
                unsafe { libc::madvise(a0 as *mut libc::c_void, a1 - a0, libc::MADV_HUGEPAGE) };
            }
        }
        Uninit { v, len }
    }
    pub fn ptr(&mut self) -> SharedMut<T> {
        // SAFETY: the capacity holds `len` values; they are only written through this view before `done`.
        unsafe { SharedMut::from_raw(self.v.as_mut_ptr(), self.len) }
    }
    /// # Safety
    /// Every index was written.
    pub unsafe fn done(mut self) -> Vec<T> {
        self.v.set_len(self.len);
        self.v
    }
}
