//! `render` and `eval` on a full disk, for real: a tmpfs mounted in a mount namespace of the test's own
//! (`unshare -m`, which needs root or CAP_SYS_ADMIN; `unshare -Urm` is tried for other users), its size set just
//! short of what the run needs. The error names the path and says the disk is full, no half-written file is left,
//! the previous render is byte for byte what it was, and once there is space the same command finishes with the
//! results of a run on a roomy disk.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

mod common;

const INNER: &str = "MVSPLAT360_DISK_FULL_DIR";
const PAGE: u64 = 4096;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_mvsplat360"))
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Runs the test `name` again inside its own mount namespace with a tmpfs on `dir/disk`; true when this is
/// that inner run (the caller then does the work).
fn in_namespace(name: &str) -> Option<PathBuf> {
    if let Some(dir) = std::env::var_os(INNER) {
        return Some(PathBuf::from(dir));
    }
    let d = tempfile::tempdir().unwrap();
    std::fs::create_dir(d.path().join("disk")).unwrap();
    let script = r#"mount -t tmpfs -o size=64m none "$1/disk" && exec "$2" --exact "$3" --nocapture --test-threads 1"#;
    let root = std::fs::read_to_string("/proc/self/status").is_ok_and(|s| s.lines().any(|l| l.starts_with("Uid:") && l.split_whitespace().nth(1) == Some("0")));
    let flags = if root { "-m" } else { "-Urm" };
    let o = Command::new("unshare")
        .args([flags, "sh", "-c", script, "sh"])
        .arg(d.path())
        .arg(std::env::current_exe().unwrap())
        .arg(name)
        .env(INNER, d.path())
        .output()
        .expect("`unshare` (util-linux) is needed for the disk-full tests");
    let text = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert!(o.status.success(), "unshare {flags} (root or CAP_SYS_ADMIN, or user namespaces) with a tmpfs: {text}");
    assert!(text.contains("1 passed"), "the inner test did not run: {text}");
    None
}

/// Bytes in use on the tmpfs at `disk`.
fn used(disk: &Path) -> u64 {
    let o = Command::new("df").args(["-B1", "--output=used"]).arg(disk).output().unwrap();
    String::from_utf8_lossy(&o.stdout).lines().nth(1).and_then(|l| l.trim().parse().ok()).expect("df --output=used")
}

/// Gives the tmpfs `limit` bytes in all (whole pages).
fn resize(disk: &Path, limit: u64) {
    let size = limit.div_ceil(PAGE) * PAGE;
    let s = Command::new("mount").args(["-o", &format!("remount,size={size}")]).arg(disk).status().unwrap();
    assert!(s.success(), "remount {size}");
}

/// Every file under `dir` by relative path (`/`-separated), outside `.render/`, with its bytes.
fn tree(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    fn walk(root: &Path, d: &Path, m: &mut BTreeMap<String, Vec<u8>>) {
        for e in std::fs::read_dir(d).unwrap().flatten() {
            let p = e.path();
            let rel = p.strip_prefix(root).unwrap().to_string_lossy().replace('\\', "/");
            if rel.starts_with(".render") {
                continue;
            }
            if p.is_dir() {
                walk(root, &p, m);
            } else {
                m.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    let mut m = BTreeMap::new();
    walk(dir, dir, &mut m);
    m
}

/// What the files take on a tmpfs: whole pages.
fn pages(files: &BTreeMap<String, Vec<u8>>, pick: impl Fn(&str) -> bool) -> u64 {
    files.iter().filter(|(k, _)| pick(k)).map(|(_, v)| (v.len() as u64).div_ceil(PAGE) * PAGE).sum()
}

/// Any temporary file left anywhere under `dir` (`.render/` included).
fn partials(dir: &Path) -> Vec<PathBuf> {
    let mut v = Vec::new();
    if let Ok(rd) = std::fs::read_dir(dir) {
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                v.extend(partials(&p));
            } else if p.to_string_lossy().contains(".partial") {
                v.push(p);
            }
        }
    }
    v
}

fn render(out: &Path, orbit: &str) -> std::process::Output {
    // The shipped model (no refiner): the run writes cameras, Gaussians, frames and the videos, in that order.
    bin()
        .args(["--quiet", "render"])
        .arg(root().join("assets/woodbox"))
        .args(["--orbit", orbit, "--num-context", "3", "--fit-steps", "0", "--out"])
        .arg(out)
        .output()
        .unwrap()
}

fn ok(o: std::process::Output) {
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// Fails for want of space: exit 1, the disk-full message naming a path under `out`, nothing half-written, the
/// previous render (`before`) untouched.
fn fails_full(o: std::process::Output, out: &Path, before: &BTreeMap<String, Vec<u8>>, what: &str) {
    let err = String::from_utf8_lossy(&o.stderr);
    eprintln!("{what}: {err}");
    assert_eq!(o.status.code(), Some(1), "{what}: {err}");
    assert!(err.contains("the disk is full") && err.contains(&out.display().to_string()), "{what}: {err}");
    assert!(err.contains(what), "{what}: the error names another file: {err}");
    assert!(partials(out).is_empty(), "{what}: {:?}", partials(out));
    assert!(!out.join(".render/stage").exists(), "{what}: the failed render left its stage");
    assert!(tree(out) == *before, "{what}: the previous render changed");
}

#[test]
fn a_render_on_a_full_disk_keeps_the_previous_one() {
    let Some(dir) = in_namespace("a_render_on_a_full_disk_keeps_the_previous_one") else { return };
    let disk = dir.join("disk");
    let out = disk.join("out");
    // The new render on a roomy disk, for its sizes and its bytes.
    let reference = dir.join("ref");
    ok(render(&reference, "12"));
    let want = tree(&reference);
    let video = pages(&want, |k| k.ends_with(".mp4"));
    // Half the videos plus the 4 pages of slack below must stay short of them.
    assert!(video >= 12 * PAGE, "the videos are too small to fill the disk part way: {video} bytes");

    ok(render(&out, "6"));
    let before = tree(&out);
    let base = used(&disk);
    // Room for the cameras and the Gaussians and half the frames: it fails writing a frame.
    let ahead = pages(&want, |k| !k.starts_with("frames/") && !k.ends_with(".mp4") && k != "run.json");
    resize(&disk, base + ahead + 4 * PAGE + pages(&want, |k| k.starts_with("frames/")) / 2);
    fails_full(render(&out, "12"), &out, &before, "frames/");
    // Room for all but half the videos: it fails writing one.
    resize(&disk, base + pages(&want, |k| !k.ends_with(".mp4") && k != "run.json") + 4 * PAGE + video / 2);
    fails_full(render(&out, "12"), &out, &before, ".mp4");
    // Space again: the same command gives the roomy disk's render.
    resize(&disk, 64 << 20);
    ok(render(&out, "12"));
    let got = tree(&out);
    assert_eq!(got.keys().collect::<Vec<_>>(), want.keys().collect::<Vec<_>>());
    for (k, v) in &want {
        if k != "run.json" {
            assert!(got[k] == *v, "{k} differs from the render on a roomy disk");
        }
    }
}

#[test]
fn an_eval_on_a_full_disk_keeps_its_finished_scenes_and_goes_on() {
    let Some(dir) = in_namespace("an_eval_on_a_full_disk_keeps_its_finished_scenes_and_goes_on") else { return };
    let disk = dir.join("disk");
    let (data, empty, m, index) = common::setup(&dir);
    let eval = |out: &Path| common::eval_cmd(&empty, &data, &index, &m, out).output().unwrap();
    let reference = dir.join("eval-ref");
    ok(eval(&reference));
    let want = tree(&reference);
    let out = disk.join("eval");
    let base = used(&disk);
    // Room for about half of what the evaluation writes.
    resize(&disk, base + pages(&want, |_| true) / 2);
    let o = eval(&out);
    let err = String::from_utf8_lossy(&o.stderr);
    eprintln!("{err}");
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("the disk is full") && err.contains(&out.display().to_string()) && err.contains("run the same command again"), "{err}");
    assert!(partials(&out).is_empty(), "{:?}", partials(&out));
    assert!(!out.join("metrics.json").exists(), "tables of an unfinished evaluation");
    // What is there is whole: each record and image as on the roomy disk.
    let part = tree(&out);
    assert!(part.keys().any(|k| k.ends_with(".png")), "nothing was written before the disk filled: {:?}", part.keys());
    for (k, v) in &part {
        if k.ends_with(".png") {
            assert!(want.get(k) == Some(v), "{k} is not the roomy disk's");
        } else if k.ends_with(".json") {
            let _: serde_json::Value = serde_json::from_slice(v).unwrap_or_else(|e| panic!("{k}: {e}"));
        }
    }
    resize(&disk, 64 << 20);
    ok(eval(&out));
    let got = tree(&out);
    let pngs = |t: &BTreeMap<String, Vec<u8>>| t.iter().filter(|(k, _)| k.ends_with(".png")).map(|(k, v)| (k.clone(), v.clone())).collect::<Vec<_>>();
    assert!(pngs(&got) == pngs(&want), "the images differ from the roomy disk's");
    let table = |t: &BTreeMap<String, Vec<u8>>| serde_json::from_slice::<serde_json::Value>(&t["metrics.json"]).unwrap()["methods"].clone();
    assert_eq!(table(&got), table(&want));
}
