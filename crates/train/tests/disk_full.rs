//! A checkpoint written to a full disk, for real: a 400 KiB tmpfs mounted in a mount namespace of this test's own
//! (`unshare -m`, which needs root or CAP_SYS_ADMIN; `unshare -Urm` is tried for other users). The first
//! checkpoint fits, the second cannot: its error names the path and the space it needs, nothing of it is left,
//! and the first still loads whole.

use std::path::Path;
use std::process::Command;

use candle_core::{Device, Tensor};
use mvsplat360_train::checkpoint::{self, State};

const INNER: &str = "MVSPLAT360_DISK_FULL_DIR";

fn tensors(v: f32) -> Vec<(String, Tensor)> {
    // 128 KiB of f32.
    vec![("w".to_string(), Tensor::full(v, (256, 128), &Device::Cpu).unwrap())]
}

fn state(step: u64) -> State {
    State { step, seed: 1, config: "x = 1".into(), train_seconds: 0.0, world: Some(1), files: Default::default() }
}

fn on_the_full_disk(out: &Path) {
    // 2 × 128 KiB per checkpoint: one fits in 400 KiB, two do not.
    checkpoint::save(out, &state(1), &tensors(1.0), &tensors(0.5), 3).unwrap();
    let e = checkpoint::save(out, &state(2), &tensors(2.0), &tensors(0.7), 3).unwrap_err().to_string();
    assert!(e.contains(&out.display().to_string()) && e.contains("needs about 263 KB"), "{e}");
    let left: Vec<String> = std::fs::read_dir(checkpoint::dir(out)).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    assert_eq!(left, ["step-0000001"], "the failed checkpoint left files");
    let l = checkpoint::load_latest(out).unwrap().unwrap();
    assert_eq!(l.state.step, 1);
    assert_eq!(l.model["w"].flatten_all().unwrap().to_vec1::<f32>().unwrap()[0], 1.0);
}

#[test]
fn a_checkpoint_on_a_full_disk() {
    if let Some(dir) = std::env::var_os(INNER) {
        on_the_full_disk(Path::new(&dir));
        return;
    }
    let d = tempfile::tempdir().unwrap();
    let exe = std::env::current_exe().unwrap();
    let script = r#"mount -t tmpfs -o size=400k none "$1" && exec "$2" --exact a_checkpoint_on_a_full_disk --nocapture --test-threads 1"#;
    let root = std::fs::read_to_string("/proc/self/status").is_ok_and(|s| s.lines().any(|l| l.starts_with("Uid:") && l.split_whitespace().nth(1) == Some("0")));
    let flags = if root { "-m" } else { "-Urm" };
    let o = Command::new("unshare")
        .args([flags, "sh", "-c", script, "sh"])
        .arg(d.path())
        .arg(&exe)
        .env(INNER, d.path())
        .output()
        .expect("`unshare` (util-linux) is needed for the disk-full test");
    let text = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert!(o.status.success(), "unshare {flags} (root or CAP_SYS_ADMIN, or user namespaces) with a tmpfs: {text}");
    assert!(text.contains("1 passed"), "the inner test did not run: {text}");
}
