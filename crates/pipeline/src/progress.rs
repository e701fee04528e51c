//! How long runs report progress: the CLI draws bars, tests and library callers use [`Silent`].

/// Progress of a long run (the CLI draws bars; tests use [`Silent`]).
pub trait Progress: Sync {
    /// A stage starts with `total` units of work (0 = unknown).
    fn begin(&self, stage: &str, total: u64);
    fn advance(&self, n: u64);
    fn end(&self);
    /// A one-line note (e.g. which weights are loaded).
    fn note(&self, msg: &str);
}

/// No progress output.
pub struct Silent;
impl Progress for Silent {
    fn begin(&self, _: &str, _: u64) {}
    fn advance(&self, _: u64) {}
    fn end(&self) {}
    fn note(&self, _: &str) {}
}
