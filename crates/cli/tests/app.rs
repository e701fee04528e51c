//! `mvsplat360 app` over plain TCP/HTTP: refused requests write nothing (no token, a foreign Origin or Host);
//! an upload over `--max-upload` is 413 with nothing kept; a path-traversal name and a file that is no photo are
//! refused; a job on the bundled scene (`assets/woodbox`, shipped model) is held at a stage by the test hook,
//! cancelled (its process group gone, no half result in its output), resumed and finished, all seen through the
//! event stream; `app` and `view` serve at once; a taken port gives the one-line message.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

mod served;
use served::{root, Killed};

/// Start `mvsplat360 ARGS` (a server) and read its address from its first stdout line.
fn serve(args: &[&str], env: &[(&str, &Path)]) -> (Killed, u16) {
    let mut c = Command::new(env!("CARGO_BIN_EXE_mvsplat360"));
    c.args(args).stdout(Stdio::piped()).stderr(Stdio::inherit());
    for (k, v) in env {
        c.env(k, v);
    }
    let mut child = c.spawn().unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let url = line.split_whitespace().find(|w| w.starts_with("http://127.0.0.1:")).unwrap_or_else(|| panic!("no address in {line:?}"));
    let port = url.trim_start_matches("http://127.0.0.1:").trim_end_matches('/').parse().unwrap();
    (Killed(child), port)
}

fn app(workdir: &Path, extra: &[&str], env: &[(&str, &Path)]) -> (Killed, u16) {
    let mut args = vec!["app", "--port", "0", "--workdir", workdir.to_str().unwrap()];
    args.extend(extra);
    serve(&args, env)
}

/// One request (`Connection: close`): status and body.
fn request(port: u16, method: &str, path: &str, headers: &[(&str, &str)], body: &[u8]) -> (u16, Vec<u8>) {
    let mut s = TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let mut head = format!("{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\nContent-Length: {}\r\n", body.len());
    for (k, v) in headers {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    head.push_str("\r\n");
    s.write_all(head.as_bytes()).unwrap();
    let _ = s.write_all(body);
    let mut buf = Vec::new();
    let _ = s.read_to_end(&mut buf);
    let text = String::from_utf8_lossy(&buf);
    let status = text.split_whitespace().nth(1).and_then(|c| c.parse().ok()).unwrap_or_else(|| panic!("no answer to {method} {path}: {text:?}"));
    let at = buf.windows(4).position(|w| w == b"\r\n\r\n").map_or(buf.len(), |p| p + 4);
    (status, buf[at..].to_vec())
}

fn token(port: u16) -> String {
    let (code, page) = request(port, "GET", "/", &[], b"");
    assert_eq!(code, 200);
    let page = String::from_utf8(page).unwrap();
    let at = page.find("name=\"mvsplat360-token\" content=\"").expect("the page carries its token") + 33;
    page[at..at + 32].to_string()
}

fn json(body: &[u8]) -> serde_json::Value {
    serde_json::from_slice(body).unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(body)))
}

/// Files under `dir` (recursively), as paths relative to it.
fn files(dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            if e.path().is_dir() {
                stack.push(e.path());
            } else {
                out.push(e.path().strip_prefix(dir).unwrap().display().to_string());
            }
        }
    }
    out
}

#[test]
fn refused_requests_write_nothing_and_uploads_are_checked() {
    let tmp = tempfile::tempdir().unwrap();
    let work = tmp.path().join("work");
    let (_app, port) = app(&work, &["--max-upload", "100K"], &[]);
    let tok = token(port);
    let t = ("X-Mvsplat360-Token", tok.as_str());
    // No token, a wrong one, a foreign Origin, a foreign Host: 403, before any route.
    assert_eq!(request(port, "POST", "/api/uploads", &[], b"").0, 403);
    assert_eq!(request(port, "POST", "/api/uploads", &[("X-Mvsplat360-Token", "0123456789abcdef0123456789abcdef")], b"").0, 403);
    assert_eq!(request(port, "POST", "/api/uploads", &[t, ("Origin", "http://evil.example")], b"").0, 403);
    let job = br#"{"scene": "/tmp", "settings": {}}"#;
    assert_eq!(request(port, "POST", "/api/jobs", &[("Origin", "http://evil.example")], job).0, 403);
    let mut s = TcpStream::connect(("127.0.0.1", port)).unwrap();
    write!(
        s,
        "POST /api/jobs HTTP/1.1\r\nHost: evil.example:{port}\r\nX-Mvsplat360-Token: {tok}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        job.len()
    )
    .unwrap();
    s.write_all(job).unwrap();
    let mut answer = String::new();
    let _ = s.read_to_string(&mut answer);
    assert!(answer.starts_with("HTTP/1.1 403"), "{answer}");
    assert_eq!(request(port, "PUT", "/api/uploads/x/a.jpg", &[], b"abc").0, 403);
    // Opening the page and the job list, and every refusal above, wrote nothing.
    assert_eq!(request(port, "GET", "/api/jobs", &[], b"").0, 200);
    assert!(!work.exists(), "refused requests wrote {:?}", files(&work));

    let up = json(&request(port, "POST", "/api/uploads", &[t], b"").1)["id"].as_str().unwrap().to_string();
    assert!(!work.exists(), "asking for an upload id writes nothing");
    // Over --max-upload (100 KiB): 413, nothing kept.
    let big = vec![0u8; 150 << 10];
    let (code, msg) = request(port, "PUT", &format!("/api/uploads/{up}/big.jpg"), &[t], &big);
    assert_eq!(code, 413, "{}", String::from_utf8_lossy(&msg));
    assert!(files(&work).is_empty(), "an upload over the limit left {:?}", files(&work));
    // Traversal names: refused; nothing written outside (or inside).
    for name in ["..%2Fevil.jpg", "%2E%2E", ".hidden.jpg", "a%2Fb.jpg", "..%5Cevil.jpg"] {
        let (code, _) = request(port, "PUT", &format!("/api/uploads/{up}/{name}"), &[t], b"xx");
        assert_eq!(code, 400, "{name}");
    }
    assert_eq!(request(port, "PUT", &format!("/api/uploads/..%2F..%2F{up}/a.jpg"), &[t], b"xx").0, 404);
    assert!(!tmp.path().join("evil.jpg").exists() && !work.join("evil.jpg").exists());
    // Not a photo (by its content), not a file kind taken: refused, removed.
    assert_eq!(request(port, "PUT", &format!("/api/uploads/{up}/fake.jpg"), &[t], b"not a jpeg at all").0, 415);
    assert_eq!(request(port, "PUT", &format!("/api/uploads/{up}/run.sh"), &[t], b"echo").0, 415);
    assert!(files(&work).is_empty(), "refused files were kept: {:?}", files(&work));
    // A real photo is kept; an upload id nobody asked for is not one.
    let photo = std::fs::read(root().join("assets/woodbox/images/000.jpg")).unwrap();
    assert_eq!(request(port, "PUT", &format!("/api/uploads/{up}/000.jpg"), &[t], &photo).0, 200);
    assert_eq!(request(port, "PUT", "/api/uploads/ffffffffffffffff/000.jpg", &[t], &photo).0, 404);
    assert_eq!(files(&work), vec![format!(".staging/{up}/000.jpg")]);
    // A job with a value that would pass for a flag: refused, no job folder.
    let bad = format!(r#"{{"upload": "{up}", "settings": {{"weights": "--out=/tmp/x"}}}}"#);
    assert_eq!(request(port, "POST", "/api/jobs", &[t], bad.as_bytes()).0, 400);
    assert!(!work.join("jobs").exists());

    // A video is probed with ffprobe: a fake one refused and removed, a real one kept; photos and a video in one
    // upload make no job.
    let up2 = json(&request(port, "POST", "/api/uploads", &[t], b"").1)["id"].as_str().unwrap().to_string();
    assert_eq!(request(port, "PUT", &format!("/api/uploads/{up2}/fake.mp4"), &[t], b"not a video at all").0, 415);
    let clip = tmp.path().join("clip.mp4");
    let made = std::process::Command::new("ffmpeg")
        .args(["-loglevel", "error", "-f", "lavfi", "-i", "testsrc=size=64x48:rate=5", "-t", "1", "-pix_fmt", "yuv420p"])
        .arg(&clip)
        .status()
        .expect("ffmpeg (scripts/test installs it)");
    assert!(made.success());
    assert_eq!(request(port, "PUT", &format!("/api/uploads/{up2}/clip.mp4"), &[t], &std::fs::read(&clip).unwrap()).0, 200);
    assert!(files(&work).contains(&format!(".staging/{up2}/clip.mp4")) && !files(&work).iter().any(|f| f.ends_with("fake.mp4")));
    assert_eq!(request(port, "PUT", &format!("/api/uploads/{up2}/000.jpg"), &[t], &photo).0, 200);
    let (code, msg) = request(port, "POST", "/api/jobs", &[t], format!(r#"{{"upload": "{up2}", "settings": {{}}}}"#).as_bytes());
    assert_eq!(code, 400, "{}", String::from_utf8_lossy(&msg));
    assert!(String::from_utf8_lossy(&msg).contains("not both"));
    // A scene folder that is not there: refused, no job.
    let missing = format!(r#"{{"scene": "{}", "settings": {{}}}}"#, tmp.path().join("nope").display());
    assert_eq!(request(port, "POST", "/api/jobs", &[t], missing.as_bytes()).0, 400);
    assert!(files(&work.join("jobs")).is_empty(), "refused jobs left {:?}", files(&work.join("jobs")));
}

/// Events of `/api/events` as (type, JSON data), read until `until` says stop (or the deadline fails the test).
fn watch(port: u16, since: u64, deadline: Duration, mut until: impl FnMut(&str, &serde_json::Value) -> bool) {
    let mut s = TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    write!(s, "GET /api/events?lastEventId={since} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n").unwrap();
    let t0 = Instant::now();
    let mut r = BufReader::new(s);
    let (mut event, mut line) = (String::new(), String::new());
    loop {
        assert!(t0.elapsed() < deadline, "no end within {deadline:?}");
        line.clear();
        assert!(r.read_line(&mut line).unwrap() > 0, "the event stream closed");
        let l = line.trim_end();
        if let Some(e) = l.strip_prefix("event: ") {
            event = e.to_string();
        } else if let Some(d) = l.strip_prefix("data: ") {
            if until(&event, &serde_json::from_str(d).unwrap()) {
                return;
            }
        }
    }
}

fn group_alive(pid: i32) -> bool {
    // SAFETY: signal 0 checks only.
    unsafe { libc::kill(-pid, 0) == 0 }
}

#[test]
fn a_job_on_the_bundled_scene_is_held_cancelled_resumed_and_viewed() {
    let t_all = Instant::now();
    let tmp = tempfile::tempdir().unwrap();
    let work = tmp.path().join("work");
    let hold = tmp.path().join("hold");
    std::fs::write(&hold, b"").unwrap();
    let at = Path::new("fitting");
    let (_app, port) = app(&work, &[], &[("MVSPLAT360_HOLD_AT", at), ("MVSPLAT360_HOLD_WHILE", &hold)]);
    let tok = token(port);
    let t = ("X-Mvsplat360-Token", tok.as_str());
    let up = json(&request(port, "POST", "/api/uploads", &[t], b"").1)["id"].as_str().unwrap().to_string();
    let scene = root().join("assets/woodbox");
    let mut names = vec![scene.join("transforms.json")];
    names.extend(std::fs::read_dir(scene.join("images")).unwrap().map(|e| e.unwrap().path()));
    for p in &names {
        let name = p.file_name().unwrap().to_str().unwrap();
        let (code, msg) = request(port, "PUT", &format!("/api/uploads/{up}/{name}"), &[t], &std::fs::read(p).unwrap());
        assert_eq!(code, 200, "{name}: {}", String::from_utf8_lossy(&msg));
    }
    let since = json(&request(port, "GET", "/api/jobs", &[], b"").1)["event_id"].as_u64().unwrap();
    let new = format!(r#"{{"upload": "{up}", "settings": {{"orbit_frames": 4, "refiner_steps": 0, "device": "cpu"}}}}"#);
    let (code, j) = request(port, "POST", "/api/jobs", &[t], new.as_bytes());
    assert_eq!(code, 201, "{}", String::from_utf8_lossy(&j));
    let id = json(&j)["id"].as_str().unwrap().to_string();
    assert!(!work.join(".staging").join(&up).exists(), "the upload became the job's folder");
    assert!(work.join("jobs").join(&id).join("input/images/000.jpg").is_file(), "photos placed where transforms.json names them");

    // Held at the stage: its progress came over the stream (an earlier stage advanced to its end).
    let (mut advanced, mut pid) = (false, 0);
    watch(port, since, Duration::from_secs(120), |ev, d| {
        if ev == "job" {
            let stages = d["stages"].as_array().unwrap();
            advanced |= stages.iter().any(|s| s["total"].as_u64() > Some(0) && s["pos"] == s["total"]);
            pid = d["pid"].as_i64().unwrap_or(pid as i64) as i32;
            return stages.last().is_some_and(|s| s["name"] == "fitting");
        }
        false
    });
    assert!(advanced && pid > 0);
    let since = json(&request(port, "GET", "/api/jobs", &[], b"").1)["event_id"].as_u64().unwrap();
    assert_eq!(request(port, "POST", &format!("/api/jobs/{id}/cancel"), &[t], b"").0, 200);
    watch(port, since, Duration::from_secs(30), |ev, d| ev == "job" && d["state"] == "cancelled");
    assert!(!group_alive(pid), "the job's process group outlived its cancel");
    let out = work.join("jobs").join(&id).join("out");
    for f in ["gaussians.ply", "run.json", "cameras.json", "video.mp4"] {
        assert!(!out.join(f).exists(), "a cancelled job left a half result: {f}");
    }
    assert!(files(&out).iter().all(|f| !f.ends_with(".partial")), "{:?}", files(&out));

    // Lift the hold and resume: it finishes.
    std::fs::remove_file(&hold).unwrap();
    let since = json(&request(port, "GET", "/api/jobs", &[], b"").1)["event_id"].as_u64().unwrap();
    assert_eq!(request(port, "POST", &format!("/api/jobs/{id}/resume"), &[t], b"").0, 200);
    let mut end = String::new();
    watch(port, since, Duration::from_secs(180), |ev, d| {
        end = d["state"].as_str().unwrap_or("").to_string();
        ev == "job" && matches!(end.as_str(), "done" | "failed")
    });
    let job = json(&request(port, "GET", &format!("/api/jobs/{id}"), &[], b"").1);
    assert_eq!(end, "done", "the job ended {end}: {}\nlog:\n{}", job["error"], job["log"]);
    assert_eq!(std::fs::read_to_string(work.join("jobs").join(&id).join("job.json")).map(|s| json(s.as_bytes())["state"].clone()).unwrap(), "done");
    // The result is served by the app's viewer route.
    let (code, m) = request(port, "GET", &format!("/jobs/{id}/view/manifest.json"), &[], b"");
    assert_eq!(code, 200);
    assert_eq!(json(&m)["frames"]["gsplat"].as_array().map(Vec::len), Some(4));
    assert_eq!(request(port, "GET", &format!("/jobs/{id}/view/data/gaussians.ply"), &[], b"").0, 200);
    assert_eq!(request(port, "GET", &format!("/jobs/{id}/view/data/..%2F..%2Fjob.json"), &[], b"").0, 400);
    assert_eq!(request(port, "GET", "/jobs/..%2F/view/manifest.json", &[], b"").0, 404);

    // `view` on the job's output serves beside the app.
    let (_view, vport) = serve(&["view", out.to_str().unwrap(), "--port", "0"], &[]);
    assert_eq!(request(vport, "GET", "/manifest.json", &[], b"").0, 200);
    assert_eq!(request(port, "GET", "/api/jobs", &[], b"").0, 200);
    eprintln!("job held, cancelled, resumed, done: {:.1} s", t_all.elapsed().as_secs_f64());
}

#[test]
fn a_restarted_app_lists_an_interrupted_job_and_a_taken_port_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    let work = tmp.path().join("work");
    let dir = work.join("jobs/job-0007");
    std::fs::create_dir_all(&dir).unwrap();
    let j = serde_json::json!({"id": "job-0007", "created": 1, "input": "a scene", "scene": "/nowhere", "settings": {},
        "state": "running", "error": null, "stages": [], "pid": 12345678, "resume": false, "log": []});
    std::fs::write(dir.join("job.json"), j.to_string()).unwrap();
    let (_app, port) = app(&work, &[], &[]);
    let list = json(&request(port, "GET", "/api/jobs", &[], b"").1);
    assert_eq!(list["jobs"][0]["state"], "interrupted", "{list}");
    assert_eq!(list["jobs"][0]["resume"], true);

    let taken = TcpListener::bind("127.0.0.1:0").unwrap();
    let p = taken.local_addr().unwrap().port().to_string();
    let o = Command::new(env!("CARGO_BIN_EXE_mvsplat360")).args(["app", "--port", &p, "--workdir"]).arg(&work).output().unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(err.contains(&p) && err.contains("--port"), "{err}");
}
