//! Two processes ask for the same file at once: one transfer; the other waits on the `.locks` flock and links the
//! blob the first wrote. The processes are this test binary itself, run as `child_process_helper`.

mod common;
use common::*;
use mvsplat360_hub::{Hub, HubConfig, HubFile, Progress};
use std::process::Command;

struct Print;
impl Progress for Print {
    fn note(&self, m: &str) {
        println!("NOTE {m}");
    }
}

/// Does nothing in a normal run; in a child (HUB_CHILD_ENDPOINT set) fetches the file and prints its path.
#[test]
fn child_process_helper() {
    let Ok(endpoint) = std::env::var("HUB_CHILD_ENDPOINT") else { return };
    let hub = Hub::new(HubConfig {
        endpoint,
        cache_dir: std::env::var("HUB_CHILD_CACHE").unwrap().into(),
        token: None,
        token_path: "/nonexistent".into(),
        offline: false,
    });
    let f = HubFile { repo: "owner/model".into(), revision: "main".into(), path: Some("model.pt".into()) };
    let p = hub.fetch(&f, &Print).unwrap();
    println!("PATH {}", p.display());
}

#[test]
fn two_processes_one_transfer() {
    let s = StandIn::start();
    let big = bytes(2_000_000, 21);
    s.add("owner/model", &[("model.pt", &big, true)]);
    // The first body stops halfway until both processes have asked for the file's metadata.
    s.set(|st| st.hold = Some(("model.pt".into(), 2)));
    let tmp = tempfile::tempdir().unwrap();
    let exe = std::env::current_exe().unwrap();
    let children: Vec<_> = (0..2)
        .map(|_| {
            Command::new(&exe)
                .args(["--exact", "child_process_helper", "--nocapture", "--test-threads=1"])
                .env("HUB_CHILD_ENDPOINT", &s.endpoint)
                .env("HUB_CHILD_CACHE", tmp.path())
                .stdout(std::process::Stdio::piped())
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    let mut paths = Vec::new();
    for c in children {
        let out = c.wait_with_output().unwrap();
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(out.status.success(), "{text}\n{}", String::from_utf8_lossy(&out.stderr));
        eprintln!("{}", text.lines().filter(|l| l.contains("NOTE ")).collect::<Vec<_>>().join("\n"));
        paths.push(text.lines().find_map(|l| l.split("PATH ").nth(1)).unwrap().to_string());
    }
    assert_eq!(paths[0], paths[1]);
    assert_eq!(std::fs::read(&paths[0]).unwrap(), big);
    let log = s.log();
    let heads = log.iter().filter(|r| r.method == "HEAD").count();
    let gets = log.iter().filter(|r| r.method == "GET").count();
    assert_eq!((heads, gets), (2, 1), "{log:?}");
    assert!(!tree(tmp.path()).iter().any(|p| p.contains(".incomplete")));
}
