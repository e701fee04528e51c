//! Python's `huggingface_hub` and this crate share one cache through the stand-in: each downloads some files,
//! then each finds the other's files offline, at the same paths. Needs python3 with huggingface_hub (scripts/test
//! installs it); without it this test fails saying how to install it.

mod common;
use common::*;
use mvsplat360_hub::{HubFile, Quiet};
use std::path::Path;
use std::process::Command;

const REPO: &str = "owner/shared";

/// Runs `hf_hub_download` for each file in Python against the stand-in and cache; returns the paths it printed.
fn python_download(endpoint: &str, cache: &Path, home: &Path, files: &[&str], offline: bool) -> Vec<String> {
    let script = format!(
        "import sys\nfrom huggingface_hub import hf_hub_download\nfor f in {files:?}:\n    print(hf_hub_download(repo_id={REPO:?}, filename=f, revision='main'))\n"
    );
    let out = Command::new("python3")
        .args(["-c", &script])
        .env("HF_ENDPOINT", endpoint)
        .env("HF_HUB_CACHE", cache)
        .env("HF_HOME", home)
        .env("HF_HUB_OFFLINE", if offline { "1" } else { "0" })
        .env("HF_HUB_DISABLE_TELEMETRY", "1")
        .env("HF_HUB_DISABLE_UPDATE_CHECK", "1")
        .env("HF_HUB_DISABLE_PROGRESS_BARS", "1")
        .env_remove("HF_TOKEN")
        .env_remove("HUGGING_FACE_HUB_TOKEN")
        .output()
        .expect("python3 not found: install python3, then: python3 -m pip install huggingface_hub");
    assert!(out.status.success(), "python's hf_hub_download failed:\n{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap().lines().map(str::to_string).collect()
}

#[test]
fn python_and_rust_find_each_others_files_offline() {
    let check = Command::new("python3").args(["-c", "import huggingface_hub"]).output();
    assert!(
        check.as_ref().is_ok_and(|o| o.status.success()),
        "this test needs Python's huggingface_hub (scripts/test installs it): python3 -m pip install huggingface_hub"
    );
    let s = StandIn::start();
    let a = bytes(150_000, 31);
    let b = b"{\"model\": \"x\"}\n".to_vec();
    let c = bytes(90_000, 32);
    let d = bytes(4_000, 33);
    s.add(REPO, &[("a.pt", &a, true), ("conf/b.json", &b, false), ("c.pt", &c, true), ("d.bin", &d, false)]);
    let tmp = tempfile::tempdir().unwrap();
    let cache = tmp.path().join("hub");
    let home = tmp.path().join("home");

    // Rust downloads a.pt and d.bin, Python conf/b.json and c.pt, into the same cache.
    let hub = s.hub(&cache, None, false);
    let file = |p: &str| HubFile { repo: REPO.into(), revision: "main".into(), path: Some(p.into()) };
    let rust_a = hub.fetch(&file("a.pt"), &Quiet).unwrap();
    let rust_d = hub.fetch(&file("d.bin"), &Quiet).unwrap();
    let py = python_download(&s.endpoint, &cache, &home, &["conf/b.json", "c.pt"], false);
    assert_eq!(py.len(), 2);
    assert_eq!(std::fs::read(&py[0]).unwrap(), b);
    assert_eq!(std::fs::read(&py[1]).unwrap(), c);

    // One layout: the same kind of relative links, one ref, no partial file.
    let t = tree(&cache);
    let snap = format!("models--owner--shared/snapshots/{COMMIT}");
    for (p, content) in [("a.pt", &a), ("c.pt", &c)] {
        assert!(t.contains(&format!("{snap}/{p} -> ../../blobs/{}", sha256_hex(content))), "{p}: {t:#?}");
    }
    assert!(t.contains(&format!("{snap}/conf/b.json -> ../../../blobs/{}", git_blob_id(&b))), "{t:#?}");
    assert!(t.contains(&format!("{snap}/d.bin -> ../../blobs/{}", git_blob_id(&d))), "{t:#?}");
    assert!(!t.iter().any(|p| p.contains(".incomplete")), "{t:#?}");
    assert_eq!(std::fs::read_to_string(cache.join("models--owner--shared/refs/main")).unwrap(), COMMIT);

    // Offline, each finds the other's files, at the same paths.
    s.clear_log();
    let off = s.hub(&cache, None, true);
    assert_eq!(off.fetch(&file("conf/b.json"), &Quiet).unwrap().to_str().unwrap(), py[0]);
    assert_eq!(off.fetch(&file("c.pt"), &Quiet).unwrap().to_str().unwrap(), py[1]);
    let py_off = python_download(&s.endpoint, &cache, &home, &["a.pt", "d.bin"], true);
    assert_eq!(py_off, vec![rust_a.to_str().unwrap().to_string(), rust_d.to_str().unwrap().to_string()]);
    assert_eq!(std::fs::read(&py_off[0]).unwrap(), a);
    assert!(s.log().is_empty(), "offline requests: {:?}", s.log());

    // Online, Python finds Rust's blob (no transfer) and Rust finds Python's.
    let py_on = python_download(&s.endpoint, &cache, &home, &["a.pt"], false);
    assert_eq!(py_on[0], rust_a.to_str().unwrap());
    hub.fetch(&file("c.pt"), &Quiet).unwrap();
    assert!(s.gets().is_empty(), "a file was transferred again: {:?}", s.log());
}

#[test]
fn a_lock_held_by_python_is_waited_for() {
    let check = Command::new("python3").args(["-c", "import huggingface_hub, filelock"]).output();
    assert!(
        check.as_ref().is_ok_and(|o| o.status.success()),
        "this test needs Python's huggingface_hub (scripts/test installs it): python3 -m pip install huggingface_hub"
    );
    let s = StandIn::start();
    let a = bytes(50_000, 34);
    s.add(REPO, &[("a.pt", &a, true)]);
    let tmp = tempfile::tempdir().unwrap();
    let cache = tmp.path().join("hub");
    let lock = cache.join(format!(".locks/models--owner--shared/{}.lock", sha256_hex(&a)));
    std::fs::create_dir_all(lock.parent().unwrap()).unwrap();
    // Python takes the lock as hf_hub_download does (filelock), and keeps it until told on stdin.
    let script = format!(
        "import sys\nfrom filelock import FileLock\nwith FileLock({:?}):\n    print('locked', flush=True)\n    sys.stdin.readline()\n",
        lock.to_str().unwrap()
    );
    let mut py = Command::new("python3").args(["-c", &script]).stdin(std::process::Stdio::piped()).stdout(std::process::Stdio::piped()).spawn().unwrap();
    let mut line = String::new();
    std::io::BufRead::read_line(&mut std::io::BufReader::new(py.stdout.as_mut().unwrap()), &mut line).unwrap();
    assert_eq!(line.trim(), "locked");
    let notes = std::sync::Arc::new(Notes::default());
    let hub = s.hub(&cache, None, false);
    let n2 = notes.clone();
    let t = std::thread::spawn(move || hub.fetch(&HubFile { repo: REPO.into(), revision: "main".into(), path: Some("a.pt".into()) }, &*n2));
    // Wait until the download says it waits on the lock, and check nothing was transferred meanwhile.
    let t0 = std::time::Instant::now();
    while !notes.0.lock().unwrap().iter().any(|n| n.contains("waiting for another download")) {
        assert!(t0.elapsed().as_secs() < 60, "the download never waited on Python's lock");
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    assert!(s.gets().is_empty());
    std::io::Write::write_all(py.stdin.as_mut().unwrap(), b"go\n").unwrap();
    assert!(py.wait().unwrap().success());
    assert_eq!(std::fs::read(t.join().unwrap().unwrap()).unwrap(), a);
    assert_eq!(s.gets().len(), 1);
}
