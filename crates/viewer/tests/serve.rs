//! The server over real sockets: the page and the folder's files are served; path escapes in every encoding are
//! refused (the request line is sent byte for byte, as no HTTP client would normalise it); the static export.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::time::Duration;

use mvsplat360_viewer::{OutDir, Server};

const SECRET: &str = "SECRET-BESIDE-THE-FOLDER";

/// A render folder (small stand-in files) inside `root`, with a secret file beside it and a symlink out of it.
fn out_dir(root: &Path) -> std::path::PathBuf {
    let out = root.join("out");
    std::fs::create_dir_all(out.join("frames/gsplat")).unwrap();
    std::fs::write(out.join("gaussians.ply"), b"ply\nformat binary_little_endian 1.0\nend_header\n").unwrap();
    std::fs::write(
        out.join("cameras.json"),
        r#"{"cameras":[{"role":"target","c2w":[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]],"K":[[100,0,64],[0,100,32],[0,0,1]],"width":128,"height":64}]}"#,
    )
    .unwrap();
    std::fs::write(out.join("run.json"), r#"{"scene_name":"test"}"#).unwrap();
    std::fs::write(out.join("frames/gsplat/0000.png"), b"PNG0").unwrap();
    std::fs::write(out.join("video.mp4"), (0u8..=99).collect::<Vec<u8>>()).unwrap();
    std::fs::write(root.join("secret.txt"), SECRET).unwrap();
    #[cfg(unix)]
    {
        // Named like a frame, so only the "resolves inside the folder" check can stop it.
        std::os::unix::fs::symlink(root.join("secret.txt"), out.join("frames/gsplat/0001.png")).unwrap();
    }
    out
}

fn start(out: &Path) -> String {
    let server = Server::bind(OutDir::open(out).unwrap(), 0).unwrap();
    let url = server.url().trim_end_matches('/').trim_start_matches("http://").to_string();
    std::thread::spawn(move || server.serve());
    url
}

/// Send `request_target` verbatim; (status, body).
fn raw_get(addr: &str, request_target: &str, extra: &str) -> (u16, Vec<u8>) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(s, "GET {request_target} HTTP/1.1\r\nHost: {addr}\r\n{extra}Connection: close\r\n\r\n").unwrap();
    let mut buf = Vec::new();
    s.read_to_end(&mut buf).unwrap();
    let head_end = buf.windows(4).position(|w| w == b"\r\n\r\n").expect("HTTP response head");
    let head = String::from_utf8_lossy(&buf[..head_end]).to_string();
    let status: u16 = head.split(' ').nth(1).and_then(|c| c.parse().ok()).expect("status code");
    (status, buf[head_end + 4..].to_vec())
}

#[test]
fn serves_the_page_and_the_folder() {
    let t = tempfile::tempdir().unwrap();
    let addr = start(&out_dir(t.path()));
    let (st, body) = raw_get(&addr, "/", "");
    assert_eq!(st, 200);
    assert!(String::from_utf8_lossy(&body).contains("viewer.js"));
    let (st, body) = raw_get(&addr, "/viewer.js", "");
    assert_eq!(st, 200);
    assert!(body.len() > 100_000, "bundle is {} bytes", body.len());
    assert_eq!(raw_get(&addr, "/THIRD_PARTY_LICENSES.txt", "").0, 200);
    let (st, body) = raw_get(&addr, "/manifest.json", "");
    assert_eq!(st, 200);
    let m: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(m["files"]["video"], "video.mp4");
    assert!(m["files"].get("metrics").is_none());
    assert_eq!(raw_get(&addr, "/data/run.json", "").1, br#"{"scene_name":"test"}"#);
    assert_eq!(raw_get(&addr, "/data/frames/gsplat/0000.png", "").1, b"PNG0");
    assert_eq!(raw_get(&addr, "/data/frames/gsplat/0000.png?v=1", "").1, b"PNG0");
    // A video seek asks for a byte range.
    let (st, body) = raw_get(&addr, "/data/video.mp4", "Range: bytes=10-19\r\n");
    assert_eq!((st, body), (206, (10u8..20).collect::<Vec<u8>>()));
    assert_eq!(raw_get(&addr, "/data/video.mp4", "Range: bytes=500-\r\n").0, 416);
    // Files that are not the page's: not found, even inside the folder; no listings.
    for target in ["/nope", "/data/frames/gt/0000.png", "/data/frames/gsplat"] {
        assert_eq!(raw_get(&addr, target, "").0, 404, "{target}");
    }
    for target in ["/data/", "/data/frames/", "/data/frames/gsplat/"] {
        let (st, body) = raw_get(&addr, target, "");
        assert!(matches!(st, 400 | 404) && !String::from_utf8_lossy(&body).contains("0000.png"), "{target}: {st}");
    }
    std::fs::write(t.path().join("out/notes.txt"), "x").unwrap();
    assert_eq!(raw_get(&addr, "/data/notes.txt", "").0, 404);
}

#[test]
fn path_escapes_are_refused() {
    let t = tempfile::tempdir().unwrap();
    let addr = start(&out_dir(t.path()));
    let secret_dir = t.path().display().to_string();
    // (request target, status): 400 = refused as a path (the decoded path climbs, is absolute or has a backslash),
    // 404 = not a file of the page, 403 = a listed name that resolves outside the folder (symlink).
    let attempts: Vec<(String, u16)> = vec![
        ("/../secret.txt".into(), 404),
        ("/data/../secret.txt".into(), 400),
        ("/data/../../secret.txt".into(), 400),
        ("/data/frames/../../secret.txt".into(), 400),
        ("/data/%2e%2e/secret.txt".into(), 400),
        ("/data/%2E%2E/secret.txt".into(), 400),
        ("/data/.%2e/secret.txt".into(), 400),
        ("/data/..%2fsecret.txt".into(), 400),
        ("/data/..%2Fsecret.txt".into(), 400),
        ("/data/%2e%2e%2fsecret.txt".into(), 400),
        ("/data/%252e%252e/secret.txt".into(), 404), // decoded once: a folder literally named "%2e%2e"
        ("/data/..\\secret.txt".into(), 400),
        ("/data/..%5csecret.txt".into(), 400),
        ("/data/frames\\..\\..\\secret.txt".into(), 400),
        (format!("/data{secret_dir}/secret.txt"), 404), // a relative path that merely looks like one
        (format!("/data/{secret_dir}/secret.txt"), 400),
        (format!("/data/%2f{}/secret.txt", secret_dir.trim_start_matches('/')), 400),
        ("/data//etc/passwd".into(), 400),
        ("/data/%2fetc%2fpasswd".into(), 400),
        ("/etc/passwd".into(), 404),
        ("/data/C:/Windows/win.ini".into(), 400),
        ("/data/./run.json".into(), 400),
        ("/data/run.json%00.png".into(), 400),
        ("/data/frames/gsplat/0001.png".into(), 403), // the symlink out of the folder
        (format!("http://{addr}/../secret.txt"), 400),
    ];
    for (target, want) in &attempts {
        let (st, body) = raw_get(&addr, target, "");
        let text = String::from_utf8_lossy(&body);
        assert!(!text.contains(SECRET) && !text.contains("root:"), "{target} leaked: {text}");
        assert_eq!(st, *want, "{target}");
    }
    // Not served, not even the request: the server is read-only.
    let mut s = TcpStream::connect(&addr).unwrap();
    write!(s, "PUT /data/run.json HTTP/1.1\r\nHost: {addr}\r\nContent-Length: 2\r\nConnection: close\r\n\r\n{{}}").unwrap();
    let mut buf = String::new();
    s.read_to_string(&mut buf).unwrap();
    assert!(buf.starts_with("HTTP/1.1 405"), "{buf}");
    assert_eq!(std::fs::read_to_string(t.path().join("out/run.json")).unwrap(), r#"{"scene_name":"test"}"#);
}

#[test]
fn static_export_is_self_contained() {
    let t = tempfile::tempdir().unwrap();
    let out = out_dir(t.path());
    std::fs::remove_file(out.join("frames/gsplat/0001.png")).ok();
    let dir = OutDir::open(&out).unwrap();
    let site = t.path().join("site");
    mvsplat360_viewer::write_static(&dir, &site).unwrap();
    for f in [
        "index.html",
        "viewer.js",
        "THIRD_PARTY_LICENSES.txt",
        "manifest.json",
        "data/gaussians.ply",
        "data/cameras.json",
        "data/run.json",
        "data/video.mp4",
        "data/frames/gsplat/0000.png",
    ] {
        assert!(site.join(f).is_file(), "{f}");
    }
    // Again over an earlier export: fine. Into a folder with other things, or inside the render: refused.
    mvsplat360_viewer::write_static(&dir, &site).unwrap();
    let other = t.path().join("other");
    std::fs::create_dir_all(&other).unwrap();
    std::fs::write(other.join("keep.txt"), "x").unwrap();
    assert!(mvsplat360_viewer::write_static(&dir, &other).unwrap_err().to_string().contains("not empty"));
    assert!(mvsplat360_viewer::write_static(&dir, &out.join("site")).unwrap_err().to_string().contains("inside the render folder"));
}

/// Send a request with exactly these header lines (no Host unless given); the status.
fn raw_status(addr: &str, headers: &str) -> u16 {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(s, "GET /data/run.json HTTP/1.1\r\n{headers}Connection: close\r\n\r\n").unwrap();
    let mut buf = String::new();
    s.read_to_string(&mut buf).unwrap();
    buf.split(' ').nth(1).and_then(|c| c.parse().ok()).expect("status code")
}

/// DNS rebinding: a foreign name in `Host` (a web page's own domain pointed at 127.0.0.1) is refused, as is a
/// malformed one, and cross-site and foreign-origin requests (an `Origin` other than the `Host`'s own); the
/// server's address, localhost and --allow-host names are answered.
#[test]
fn foreign_hosts_and_origins_are_refused() {
    let t = tempfile::tempdir().unwrap();
    let out = out_dir(t.path());
    let addr = start(&out);
    let port = addr.rsplit(':').next().unwrap();
    assert_eq!(raw_status(&addr, &format!("Host: {addr}\r\n")), 200);
    assert_eq!(raw_status(&addr, &format!("Host: localhost:{port}\r\n")), 200);
    assert_eq!(raw_status(&addr, &format!("Host: {addr}\r\nOrigin: http://{addr}\r\nSec-Fetch-Site: same-origin\r\n")), 200);
    assert_eq!(raw_status(&addr, "Host: evil.example\r\n"), 403);
    assert_eq!(raw_status(&addr, &format!("Host: evil.example:{port}\r\n")), 403);
    assert_eq!(raw_status(&addr, "Host: 127.0.0.1:1\r\n"), 403);
    assert_eq!(raw_status(&addr, ""), 400);
    assert_eq!(raw_status(&addr, &format!("Host: {addr}\r\nOrigin: http://evil.example\r\n")), 403);
    assert_eq!(raw_status(&addr, &format!("Host: {addr}\r\nSec-Fetch-Site: cross-site\r\n")), 403);
    // Bracketed IPv6: after `]` only `:PORT` may follow.
    assert_eq!(raw_status(&addr, &format!("Host: [::1]:{port}\r\n")), 200);
    assert!(matches!(raw_status(&addr, "Host: [::1]evil.example\r\n"), 400 | 403));
    assert!(matches!(raw_status(&addr, &format!("Host: [::1]:{port}evil.example\r\n")), 400 | 403));
    // Two Host headers are one too many.
    assert_eq!(raw_status(&addr, &format!("Host: {addr}\r\nHost: evil.example\r\n")), 400);
    // The Origin must be the accepted Host's own (scheme, name and port; no port = 80).
    assert_eq!(raw_status(&addr, &format!("Host: {addr}\r\nOrigin: http://203.0.113.5\r\n")), 403);
    assert_eq!(raw_status(&addr, &format!("Host: {addr}\r\nOrigin: http://127.0.0.1\r\n")), 403);
    assert_eq!(raw_status(&addr, &format!("Host: {addr}\r\nOrigin: http://localhost:{port}\r\n")), 403);
    assert_eq!(raw_status(&addr, &format!("Host: {addr}\r\nOrigin: null\r\n")), 403);
    assert_eq!(raw_status(&addr, &format!("Host: {addr}\r\nOrigin: http://{addr}\r\nOrigin: http://203.0.113.5\r\n")), 403);
    assert_eq!(raw_status(&addr, &format!("Host: localhost:{port}\r\nOrigin: http://localhost:{port}\r\n")), 200);
    assert_eq!(raw_status(&addr, &format!("Host: [::1]:{port}\r\nOrigin: http://[::1]:{port}\r\n")), 200);
    let server = Server::bind_on(OutDir::open(&out).unwrap(), "127.0.0.1", 0, vec!["gpu-box.example".into()]).unwrap();
    let addr2 = server.url().trim_end_matches('/').trim_start_matches("http://").to_string();
    std::thread::spawn(move || server.serve());
    let port2 = addr2.rsplit(':').next().unwrap();
    assert_eq!(raw_status(&addr2, &format!("Host: gpu-box.example:{port2}\r\n")), 200);
    assert_eq!(raw_status(&addr2, &format!("Host: other.example:{port2}\r\n")), 403);
    // Behind a TLS tunnel: the page's origin is https, the Host forwarded without a port.
    assert_eq!(raw_status(&addr2, "Host: gpu-box.example\r\nOrigin: https://gpu-box.example\r\n"), 200);
    assert_eq!(raw_status(&addr2, "Host: gpu-box.example\r\nOrigin: https://other.example\r\n"), 403);
}

/// A link out of the render folder is refused by the static export, named, and nothing of it is copied.
#[cfg(unix)]
#[test]
fn static_export_refuses_links_out_of_the_folder() {
    let t = tempfile::tempdir().unwrap();
    let out = out_dir(t.path());
    let dir = OutDir::open(&out).unwrap();
    let site = t.path().join("site");
    let e = mvsplat360_viewer::write_static(&dir, &site).unwrap_err().to_string();
    assert!(e.contains("0001.png") && e.contains("outside the render folder"), "{e}");
    let copied = |d: &Path| -> bool {
        std::fs::read_dir(d).into_iter().flatten().flatten().any(|e| std::fs::read(e.path()).is_ok_and(|b| String::from_utf8_lossy(&b).contains(SECRET)))
    };
    assert!(!copied(&site.join("data/frames/gsplat")), "the secret was published");
}

/// Seconds a normal page request takes.
fn page_secs(addr: &str) -> f64 {
    let t0 = std::time::Instant::now();
    assert_eq!(raw_get(addr, "/data/run.json", "").0, 200);
    t0.elapsed().as_secs_f64()
}

/// Idle and stalled clients cannot hold the server: 50 connections open and silent, 4 requests sent halfway and
/// 4 downloads of a `gaussians.ply` larger than the sockets' buffers that are never read do not delay a normal
/// request by more than a second.
#[test]
fn idle_and_stalled_clients_do_not_hold_the_server() {
    let t = tempfile::tempdir().unwrap();
    let out = out_dir(t.path());
    std::fs::write(out.join("gaussians.ply"), vec![7u8; 48 << 20]).unwrap();
    let addr = start(&out);
    let before = page_secs(&addr);
    let idle: Vec<TcpStream> = (0..50).map(|_| TcpStream::connect(&addr).unwrap()).collect();
    let half: Vec<TcpStream> = (0..4)
        .map(|_| {
            let mut s = TcpStream::connect(&addr).unwrap();
            write!(s, "GET /data/run.json HTTP/1.1\r\nHost: {addr}\r\n").unwrap();
            s
        })
        .collect();
    let stalled: Vec<TcpStream> = (0..4)
        .map(|_| {
            let mut s = TcpStream::connect(&addr).unwrap();
            write!(s, "GET /data/gaussians.ply HTTP/1.1\r\nHost: {addr}\r\n\r\n").unwrap();
            s
        })
        .collect();
    // Let the server take them all in and fill the stalled downloads' buffers.
    std::thread::sleep(Duration::from_millis(500));
    for _ in 0..3 {
        let during = page_secs(&addr);
        assert!(during < before + 1.0, "a normal request took {during:.2} s beside idle and stalled clients ({before:.3} s alone)");
    }
    drop((idle, half, stalled));
}

/// The limits act: a connection beyond the cap gets 503; a head sent too slowly gets 408 and the connection is
/// closed; a silent connection is closed; a download the client stops reading is dropped; and a kept-alive
/// connection serves several (pipelined) requests.
#[test]
fn slow_silent_and_stalled_clients_are_dropped() {
    let t = tempfile::tempdir().unwrap();
    let out = out_dir(t.path());
    let size = 48usize << 20;
    std::fs::write(out.join("gaussians.ply"), vec![7u8; size]).unwrap();
    let limits =
        mvsplat360_viewer::Limits { head: Duration::from_millis(800), idle: Duration::from_millis(800), write: Duration::from_millis(800), connections: 6 };
    let server = Server::bind(OutDir::open(&out).unwrap(), 0).unwrap().with_limits(limits);
    let addr = server.url().trim_end_matches('/').trim_start_matches("http://").to_string();
    std::thread::spawn(move || server.serve());
    let read_all = |s: &mut TcpStream| {
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let mut b = Vec::new();
        let _ = s.read_to_end(&mut b);
        b
    };

    // Two requests on one connection, the second sent before the first is answered.
    let mut s = TcpStream::connect(&addr).unwrap();
    write!(s, "GET /data/run.json HTTP/1.1\r\nHost: {addr}\r\n\r\nGET /data/run.json HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").unwrap();
    let both = String::from_utf8_lossy(&read_all(&mut s)).to_string();
    assert_eq!(both.matches("HTTP/1.1 200 OK").count(), 2, "{both}");

    // A head trickling in: 408 once the head limit passes, then closed.
    let mut slow = TcpStream::connect(&addr).unwrap();
    let t0 = std::time::Instant::now();
    for b in format!("GET /data/run.json HTTP/1.1\r\nHost: {addr}\r\n").bytes().take(12) {
        if slow.write_all(&[b]).is_err() {
            break;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let got = String::from_utf8_lossy(&read_all(&mut slow)).to_string();
    assert!(got.starts_with("HTTP/1.1 408"), "{got}");
    assert!(t0.elapsed() < Duration::from_secs(60), "closed after {:?}: a hang", t0.elapsed());

    // Silent: closed without a word.
    let mut silent = TcpStream::connect(&addr).unwrap();
    let t0 = std::time::Instant::now();
    assert!(read_all(&mut silent).is_empty());
    assert!(t0.elapsed() < Duration::from_secs(60), "closed after {:?}: a hang", t0.elapsed());

    // A stalled download: after the write limit the server gives up, so the client gets less than the file.
    let mut stalled = TcpStream::connect(&addr).unwrap();
    write!(stalled, "GET /data/gaussians.ply HTTP/1.1\r\nHost: {addr}\r\n\r\n").unwrap();
    std::thread::sleep(Duration::from_secs(3));
    let got = read_all(&mut stalled);
    assert!(got.starts_with(b"HTTP/1.1 200") && got.len() < size, "{} of {size} bytes", got.len());

    // Over the cap: 503 at once (the dropped connections' slots are free again by now).
    let held: Vec<TcpStream> = (0..6).map(|_| TcpStream::connect(&addr).unwrap()).collect();
    std::thread::sleep(Duration::from_millis(200));
    let mut extra = TcpStream::connect(&addr).unwrap();
    let got = String::from_utf8_lossy(&read_all(&mut extra)).to_string();
    assert!(got.starts_with("HTTP/1.1 503"), "{got}");
    drop(held);
}
