//! What the tests that start a server (`app`, `view`) share: the repository root and a child process killed
//! when the test ends, passed or not.

use std::path::PathBuf;
use std::process::Child;

pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Kills the server when the test ends, passed or not.
pub struct Killed(pub Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}
