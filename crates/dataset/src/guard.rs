//! A boundary around third-party parsers fed untrusted files: a panic inside becomes an error (with the panic's
//! message) instead of ending the program, and is not printed, since the caller reports it as a bad file.

use std::cell::Cell;
use std::sync::Once;

thread_local! {
    static QUIET: Cell<bool> = const { Cell::new(false) };
}

/// `f()`, or `Err(message)` when it panics.
pub fn catch_quietly<T>(f: impl FnOnce() -> T) -> Result<T, String> {
    static HOOK: Once = Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        // Only this thread's panics inside `catch_quietly` are silenced; every other panic prints as before.
        std::panic::set_hook(Box::new(move |info| {
            if !QUIET.with(Cell::get) {
                previous(info);
            }
        }));
    });
    let was = QUIET.with(|q| q.replace(true));
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    QUIET.with(|q| q.set(was));
    r.map_err(|p| p.downcast_ref::<&str>().map(|s| s.to_string()).or_else(|| p.downcast_ref::<String>().cloned()).unwrap_or_else(|| "panic".into()))
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_panic_becomes_its_message() {
        assert_eq!(super::catch_quietly(|| 7), Ok(7));
        let e = super::catch_quietly(|| -> u8 { panic!("shift overflow at byte {}", 3) }).unwrap_err();
        assert_eq!(e, "shift overflow at byte 3");
    }
}
