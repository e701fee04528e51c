//! Downloads against the stand-in: the Python layout, redirects and the token, resume, checks, errors, offline.

mod common;
use common::*;
use mvsplat360_hub::{Error, HubFile, Quiet, Resolved};
use std::path::Path;

const REPO: &str = "owner/model";

fn file(path: &str) -> HubFile {
    HubFile { repo: REPO.into(), revision: "main".into(), path: Some(path.into()) }
}

fn no_partials(dir: &Path) -> bool {
    !tree(dir).iter().any(|p| p.contains(".incomplete"))
}

#[test]
fn first_download_in_the_python_layout_token_not_sent_to_the_lfs_host() {
    let s = StandIn::start();
    let big = bytes(300_000, 1);
    let small = b"{\"a\": 1}\n".to_vec();
    s.add(REPO, &[("model.pt", &big, true), ("sub/config.json", &small, false)]);
    let tmp = tempfile::tempdir().unwrap();
    let hub = s.hub(tmp.path(), Some("tok"), false);

    let p = hub.fetch(&file("model.pt"), &Quiet).unwrap();
    let q = hub.resolve(&format!("hf:{REPO}/sub/config.json"), &Quiet).unwrap();
    assert_eq!(std::fs::read(&p).unwrap(), big);
    let Resolved::Path(q) = q else { panic!() };
    assert_eq!(std::fs::read(&q).unwrap(), small);

    let sha = sha256_hex(&big);
    let git = git_blob_id(&small);
    let mut want = vec![
        format!(".locks/models--owner--model/{sha}.lock"),
        format!(".locks/models--owner--model/{git}.lock"),
        format!("models--owner--model/blobs/{sha}"),
        format!("models--owner--model/blobs/{git}"),
        "models--owner--model/refs/main".to_string(),
        format!("models--owner--model/snapshots/{COMMIT}/model.pt -> ../../blobs/{sha}"),
        format!("models--owner--model/snapshots/{COMMIT}/sub/config.json -> ../../../blobs/{git}"),
    ];
    want.sort();
    assert_eq!(tree(tmp.path()), want);
    assert_eq!(std::fs::read_to_string(tmp.path().join("models--owner--model/refs/main")).unwrap(), COMMIT);
    assert_eq!(p, tmp.path().join(format!("models--owner--model/snapshots/{COMMIT}/model.pt")));

    let log = s.log();
    let cdn: Vec<_> = log.iter().filter(|r| r.cdn).collect();
    assert_eq!(cdn.len(), 1, "{log:?}");
    assert_eq!(cdn[0].auth, None, "the token went to the LFS host");
    assert!(log.iter().filter(|r| !r.cdn).all(|r| r.auth.as_deref() == Some("Bearer tok")), "{log:?}");
    assert!(log.iter().all(|r| r.range.is_none()));

    // Again: one HEAD each, no transfer.
    s.clear_log();
    hub.fetch(&file("model.pt"), &Quiet).unwrap();
    hub.fetch(&file("sub/config.json"), &Quiet).unwrap();
    assert!(s.gets().is_empty(), "{:?}", s.log());
}

#[test]
fn relative_redirect_followed_with_the_token() {
    let s = StandIn::start();
    s.add(REPO, &[("a.bin", &bytes(1000, 2), false)]);
    s.set(|st| {
        st.aliases.insert("owner/old-name".into(), REPO.into());
    });
    let tmp = tempfile::tempdir().unwrap();
    let hub = s.hub(tmp.path(), Some("tok"), false);
    let p = hub.resolve("hf:owner/old-name/a.bin", &Quiet).unwrap();
    assert_eq!(p, Resolved::Path(tmp.path().join(format!("models--owner--old-name/snapshots/{COMMIT}/a.bin"))));
    let log = s.log();
    assert!(log.iter().any(|r| r.path == "/owner/model/resolve/main/a.bin" && r.method == "HEAD" && r.auth.as_deref() == Some("Bearer tok")), "{log:?}");
}

#[test]
fn a_cut_transfer_is_an_interruption_then_resumed_where_it_stopped() {
    let s = StandIn::start();
    let big = bytes(200_000, 3);
    s.add(REPO, &[("model.pt", &big, true)]);
    let tmp = tempfile::tempdir().unwrap();
    let hub = s.hub(tmp.path(), None, false);
    s.set(|st| st.cut_next_body_after = Some(70_000));
    let e = hub.fetch(&file("model.pt"), &Quiet).unwrap_err();
    assert!(matches!(e, Error::Interrupted(_)), "{e}");
    assert!(e.to_string().contains("run again to resume"), "{e}");
    let sha = sha256_hex(&big);
    let part = tmp.path().join(format!("models--owner--model/blobs/{sha}.incomplete"));
    let kept = std::fs::metadata(&part).unwrap().len();
    assert!(kept > 0 && kept <= 70_000, "{kept}");
    assert!(!tmp.path().join(format!("models--owner--model/blobs/{sha}")).exists());
    assert!(!tmp.path().join(format!("models--owner--model/snapshots/{COMMIT}/model.pt")).exists());

    s.clear_log();
    let notes = Notes::default();
    let p = hub.fetch(&file("model.pt"), &notes).unwrap();
    assert_eq!(std::fs::read(p).unwrap(), big);
    let gets = s.gets();
    assert_eq!(gets.len(), 1);
    assert_eq!(gets[0].range.as_deref(), Some(format!("bytes={kept}-").as_str()));
    assert_eq!(notes.1.lock().unwrap().clone(), vec![("model.pt".to_string(), Some(200_000), kept)]);
    assert!(no_partials(tmp.path()));
}

#[test]
fn a_server_that_ignores_range_restarts_the_file() {
    let s = StandIn::start();
    let big = bytes(90_000, 13);
    s.add(REPO, &[("model.pt", &big, true)]);
    let tmp = tempfile::tempdir().unwrap();
    let hub = s.hub(tmp.path(), None, false);
    s.set(|st| st.cut_next_body_after = Some(30_000));
    assert!(matches!(hub.fetch(&file("model.pt"), &Quiet), Err(Error::Interrupted(_))));
    s.set(|st| st.ignore_range = true);
    assert_eq!(std::fs::read(hub.fetch(&file("model.pt"), &Quiet).unwrap()).unwrap(), big);
    assert!(s.gets().last().unwrap().range.is_some());
    assert!(no_partials(tmp.path()));
}

#[test]
fn a_partial_download_left_by_python_is_resumed() {
    let s = StandIn::start();
    let big = bytes(120_000, 4);
    let small = bytes(50_000, 5);
    s.add(REPO, &[("model.pt", &big, true), ("small.bin", &small, false)]);
    let tmp = tempfile::tempdir().unwrap();
    let blobs = tmp.path().join("models--owner--model/blobs");
    std::fs::create_dir_all(&blobs).unwrap();
    // As huggingface_hub < 2 leaves it (and resumes it): blobs/<etag>.incomplete.
    let sha = sha256_hex(&big);
    std::fs::write(blobs.join(format!("{sha}.incomplete")), &big[..40_000]).unwrap();
    // As a killed huggingface_hub 2.x leaves it: blobs/<etag>.<8 hex>.incomplete.
    let git = git_blob_id(&small);
    std::fs::write(blobs.join(format!("{git}.0a1b2c3d.incomplete")), &small[..30_000]).unwrap();
    std::fs::write(blobs.join(format!("{git}.99999999.incomplete")), &small[..10_000]).unwrap();
    let hub = s.hub(tmp.path(), None, false);
    assert_eq!(std::fs::read(hub.fetch(&file("model.pt"), &Quiet).unwrap()).unwrap(), big);
    assert_eq!(std::fs::read(hub.fetch(&file("small.bin"), &Quiet).unwrap()).unwrap(), small);
    let ranges: Vec<_> = s.gets().into_iter().map(|r| r.range).collect();
    assert_eq!(ranges, vec![Some("bytes=40000-".to_string()), Some("bytes=30000-".to_string())]);
    assert!(no_partials(tmp.path()), "{:?}", tree(tmp.path()));
}

#[test]
fn a_corrupt_body_is_refused_and_nothing_is_left() {
    let s = StandIn::start();
    let big = bytes(100_000, 6);
    let small = bytes(3_000, 7);
    s.add(REPO, &[("model.pt", &big, true), ("small.bin", &small, false)]);
    s.set(|st| st.corrupt = true);
    let tmp = tempfile::tempdir().unwrap();
    let hub = s.hub(tmp.path(), None, false);
    for (name, what) in [("model.pt", "SHA-256"), ("small.bin", "git blob id")] {
        let e = hub.fetch(&file(name), &Quiet).unwrap_err();
        assert!(matches!(e, Error::Corrupt(_)), "{e}");
        let m = e.to_string();
        assert!(m.contains("corrupt") && m.contains(what) && m.contains("deleted"), "{m}");
    }
    let left: Vec<_> = tree(tmp.path()).into_iter().filter(|p| p.contains("blobs/") || p.contains("snapshots/")).collect();
    assert!(left.is_empty(), "{left:?}");
    // Served right, it downloads.
    s.set(|st| st.corrupt = false);
    assert_eq!(std::fs::read(hub.fetch(&file("model.pt"), &Quiet).unwrap()).unwrap(), big);
}

#[test]
fn gated_repositories_say_what_to_do() {
    let s = StandIn::start();
    let content = bytes(5_000, 8);
    s.add_repo(
        "meta/gated",
        Repo {
            commit: COMMIT.into(),
            files: vec![("model.pt".into(), File { content: content.clone(), lfs: true })],
            gated: Some(vec!["yes".into()]),
            ..Default::default()
        },
    );
    let tmp = tempfile::tempdir().unwrap();
    let page = format!("{}/meta/gated", s.endpoint);

    let e = s.hub(tmp.path(), None, false).resolve("hf:meta/gated/model.pt", &Quiet).unwrap_err();
    let m = e.to_string();
    assert!(matches!(e, Error::Gated(_)), "{m}");
    assert!(m.contains("gated") && m.contains(&page) && m.contains("HF_TOKEN") && m.contains("request access"), "{m}");

    let e = s.hub(tmp.path(), Some("no"), false).resolve("hf:meta/gated/model.pt", &Quiet).unwrap_err();
    let m = e.to_string();
    assert!(matches!(e, Error::Gated(_)), "{m}");
    assert!(m.contains("without access") && m.contains(&page), "{m}");

    let e = s.hub(tmp.path(), Some("invalid-xyz"), false).resolve("hf:meta/gated/model.pt", &Quiet).unwrap_err();
    assert!(matches!(e, Error::BadToken(_)), "{e}");
    assert!(e.to_string().contains("rejected the token"), "{e}");

    let p = s.hub(tmp.path(), Some("yes"), false).resolve("hf:meta/gated/model.pt", &Quiet).unwrap();
    let Resolved::Path(p) = p else { panic!() };
    assert_eq!(std::fs::read(p).unwrap(), content);
}

#[test]
fn not_found_names_the_wrong_part() {
    let s = StandIn::start();
    s.add(REPO, &[("model.pt", &bytes(100, 9), true)]);
    let tmp = tempfile::tempdir().unwrap();
    let hub = s.hub(tmp.path(), None, false);
    let err = |spec: &str| {
        let e = hub.resolve(spec, &Quiet).unwrap_err();
        assert!(matches!(e, Error::NotFound(_)), "{e}");
        e.to_string()
    };
    let m = err("hf:owner/nope/model.pt");
    assert!(m.contains("repository owner/nope not found") && m.contains("private") && m.contains("HF_TOKEN"), "{m}");
    let m = err("hf:owner/model/model.pt@v9");
    assert!(m.contains("revision \"v9\" not found in owner/model"), "{m}");
    let m = err("hf:owner/model/weights.pt");
    assert!(m.contains("weights.pt not found") && m.contains("no such file") && m.contains("tree/main"), "{m}");
    let m = err("hf:owner/nope");
    assert!(m.contains("repository owner/nope not found"), "{m}");
    assert!(no_partials(tmp.path()));
    assert!(!tmp.path().join("models--owner--model/blobs").exists());
}

#[test]
fn offline_uses_the_cache_without_a_request_or_says_where_to_place_the_file() {
    let s = StandIn::start();
    let big = bytes(10_000, 10);
    s.add(REPO, &[("model.pt", &big, true)]);
    let tmp = tempfile::tempdir().unwrap();
    s.hub(tmp.path(), None, false).fetch(&file("model.pt"), &Quiet).unwrap();
    s.clear_log();

    let off = s.hub(tmp.path(), None, true);
    let p = off.resolve(&format!("hf:{REPO}/model.pt"), &Quiet).unwrap();
    let Resolved::Path(p) = p else { panic!() };
    assert_eq!(std::fs::read(p).unwrap(), big);
    // By commit, too, and the folder.
    off.resolve(&format!("hf:{REPO}/model.pt@{COMMIT}"), &Quiet).unwrap();
    assert!(off.resolve(&format!("hf:{REPO}"), &Quiet).unwrap() == Resolved::Path(tmp.path().join(format!("models--owner--model/snapshots/{COMMIT}"))));
    assert!(s.log().is_empty(), "{:?}", s.log());

    let e = off.resolve(&format!("hf:{REPO}/other.pt@v2"), &Quiet).unwrap_err();
    let m = e.to_string();
    assert!(matches!(e, Error::Offline(_)), "{m}");
    for part in ["HF_HUB_OFFLINE", "other.pt", REPO, "revision v2", "models--owner--model", "snapshots/<commit>/other.pt", "refs/v2"] {
        assert!(m.contains(part), "{part:?} missing in: {m}");
    }
    assert!(s.log().is_empty());

    // Online, a commit already cached needs no request either.
    s.hub(tmp.path(), None, false).resolve(&format!("hf:{REPO}/model.pt@{COMMIT}"), &Quiet).unwrap();
    assert!(s.log().is_empty());
}

#[test]
fn a_file_placed_by_python_is_used_offline() {
    // The layout huggingface_hub writes (blob, relative link, ref), made by hand here; tests/interop.rs has Python
    // itself write it.
    let tmp = tempfile::tempdir().unwrap();
    let repo = tmp.path().join("models--facebook--VGGT-1B");
    let content = b"weights".to_vec();
    let etag = sha256_hex(&content);
    std::fs::create_dir_all(repo.join("blobs")).unwrap();
    std::fs::create_dir_all(repo.join("refs")).unwrap();
    std::fs::create_dir_all(repo.join(format!("snapshots/{COMMIT}"))).unwrap();
    std::fs::write(repo.join("blobs").join(&etag), &content).unwrap();
    std::fs::write(repo.join("refs/main"), COMMIT).unwrap();
    std::os::unix::fs::symlink(format!("../../blobs/{etag}"), repo.join(format!("snapshots/{COMMIT}/model.pt"))).unwrap();
    let s = StandIn::start();
    let off = s.hub(tmp.path(), None, true);
    let Resolved::Path(p) = off.resolve("vggt-1b", &Quiet).unwrap() else { panic!() };
    assert_eq!(std::fs::read(&p).unwrap(), content);
    let list = off.short_names();
    let v = list.iter().find(|e| e.entry.name == "vggt-1b").unwrap();
    assert_eq!(v.cached.as_deref(), Some(p.as_path()));
    assert_eq!(v.size, Some(content.len() as u64));
    assert!(list.iter().filter(|e| e.entry.name != "vggt-1b").all(|e| e.cached.is_none()));
    assert!(s.log().is_empty());
}

#[test]
fn hub_unreachable_falls_back_to_the_cached_snapshot_with_a_note() {
    let s = StandIn::start();
    let big = bytes(5_000, 11);
    s.add(REPO, &[("model.pt", &big, true)]);
    let tmp = tempfile::tempdir().unwrap();
    s.hub(tmp.path(), None, false).fetch(&file("model.pt"), &Quiet).unwrap();
    // A port nobody listens on.
    let dead = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        format!("http://127.0.0.1:{}", l.local_addr().unwrap().port())
    };
    let hub = mvsplat360_hub::Hub::new(mvsplat360_hub::HubConfig {
        endpoint: dead.clone(),
        cache_dir: tmp.path().to_path_buf(),
        token: None,
        token_path: "/nonexistent".into(),
        offline: false,
    });
    let notes = Notes::default();
    assert_eq!(std::fs::read(hub.fetch(&file("model.pt"), &notes).unwrap()).unwrap(), big);
    let n = notes.0.lock().unwrap().join("\n");
    assert!(n.contains("could not be reached") && n.contains(COMMIT), "{n}");
    let e = hub.fetch(&file("other.pt"), &Quiet).unwrap_err();
    assert!(matches!(e, Error::Unreachable(_)), "{e}");
    assert!(e.to_string().contains(&dead) && e.to_string().contains("other.pt of owner/model"), "{e}");
}

#[test]
fn a_repository_as_a_folder() {
    let s = StandIn::start();
    let a = bytes(20_000, 12);
    let b = b"{}".to_vec();
    s.add(REPO, &[("model.safetensors", &a, true), ("config.json", &b, false), ("sub/x.txt", b"x", false)]);
    let tmp = tempfile::tempdir().unwrap();
    let hub = s.hub(tmp.path(), None, false);
    let Resolved::Path(dir) = hub.resolve(&format!("hf:{REPO}"), &Quiet).unwrap() else { panic!() };
    assert_eq!(dir, tmp.path().join(format!("models--owner--model/snapshots/{COMMIT}")));
    assert_eq!(std::fs::read(dir.join("model.safetensors")).unwrap(), a);
    assert_eq!(std::fs::read(dir.join("config.json")).unwrap(), b);
    assert_eq!(std::fs::read(dir.join("sub/x.txt")).unwrap(), b"x");
    assert_eq!(std::fs::read_to_string(tmp.path().join("models--owner--model/refs/main")).unwrap(), COMMIT);
    // Again: the file list only, each file found by commit without a request.
    s.clear_log();
    hub.resolve(&format!("hf:{REPO}"), &Quiet).unwrap();
    let log = s.log();
    assert_eq!(log.len(), 1, "{log:?}");
    assert_eq!(log[0].path, "/api/models/owner/model/revision/main");
}

#[test]
fn names_and_local_paths() {
    let s = StandIn::start();
    s.add(REPO, &[("model.pt", b"m", false)]);
    let tmp = tempfile::tempdir().unwrap();
    let hub = s.hub(tmp.path(), None, false);
    // An existing path wins, even spelled like a name.
    let local = tmp.path().join("hf:owner");
    std::fs::create_dir_all(&local).unwrap();
    let spec = local.to_str().unwrap();
    assert_eq!(hub.resolve(spec, &Quiet).unwrap(), Resolved::Path(local.clone()));
    assert_eq!(hub.resolve("default", &Quiet).unwrap(), Resolved::ShippedDefault);
    assert_eq!(hub.resolve_or("default", Path::new("/x/models/default"), &Quiet).unwrap(), Path::new("/x/models/default"));
    // The Hub URL form, of this endpoint.
    let url = format!("{}/{REPO}/resolve/main/model.pt", s.endpoint);
    let Resolved::Path(p) = hub.resolve(&url, &Quiet).unwrap() else { panic!() };
    assert_eq!(std::fs::read(p).unwrap(), b"m");
    let e = hub.resolve("no/such/file.pt", &Quiet).unwrap_err();
    assert!(matches!(e, Error::BadName(_)) && e.to_string().contains("neither an existing file"), "{e}");
    assert!(s.log().iter().all(|r| r.path.contains("model.pt")));
}
