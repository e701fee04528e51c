//! The shared server core over real sockets, with a tiny handler of the kind `app` has: a page carrying the
//! token, `PUT /upload/NAME` into a staging folder, `POST /jobs`, and an event stream. Requests are sent byte for
//! byte, as a hostile or broken client would.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use mvsplat360_viewer::http::{Body, BodyLimits, EventSource, HttpServer, Limits, PageToken, Request, Response, Stats, TOKEN_HEADER};

const TOKEN: &str = "0123456789abcdef0123456789abcdef";
/// Long enough for any step of these tests on a loaded machine: passing it means a hang.
const HANG: Duration = Duration::from_secs(30);

struct Opts {
    limits: Limits,
    body: BodyLimits,
    heartbeat: Duration,
    max_upload: u64,
}

impl Default for Opts {
    fn default() -> Self {
        Self { limits: Limits::default(), body: BodyLimits::default(), heartbeat: Duration::from_secs(10), max_upload: 64 << 10 }
    }
}

struct Running {
    addr: String,
    stats: Stats,
    events: EventSource,
    /// Uploads are staged here; jobs are written to `jobs/`.
    staging: PathBuf,
    jobs: PathBuf,
    _root: tempfile::TempDir,
}

fn start(o: Opts) -> Running {
    let root = tempfile::tempdir().unwrap();
    let staging = root.path().join("work/.staging");
    let jobs = root.path().join("work/jobs");
    std::fs::create_dir_all(&staging).unwrap();
    std::fs::create_dir_all(&jobs).unwrap();
    let events = EventSource::new(100);
    let token = PageToken::from_string(TOKEN);
    let server = HttpServer::bind("127.0.0.1", 0).unwrap().with_token(token.clone()).with_limits(o.limits).with_body_limits(o.body).with_heartbeat(o.heartbeat);
    let addr = server.url().trim_end_matches('/').trim_start_matches("http://").to_string();
    let stats = server.stats();
    let (ev, st, jb, max) = (events.clone(), staging.clone(), jobs.clone(), o.max_upload);
    std::thread::spawn(move || {
        server.serve(move |req: &Request, body: &mut Body<'_>| -> Response {
            match (req.method.as_str(), req.path()) {
                ("GET", "/") => Response::bytes(200, "text/html; charset=utf-8", format!("<html><head>{}</head></html>", token.meta_tag()).into_bytes()),
                ("GET", "/ping") => Response::text(200, "pong"),
                ("GET", "/events") => Response::events(ev.subscribe(req.last_event_id())),
                ("PUT", p) if p.starts_with("/upload/") => match body.save_into(&st, &p["/upload/".len()..], max) {
                    Ok(path) => Response::text(201, &path.file_name().unwrap().to_string_lossy()),
                    Err(e) => e.response(),
                },
                ("POST", "/jobs") => match body.read_to_vec(4096) {
                    Ok(b) => {
                        let n = std::fs::read_dir(&jb).unwrap().count();
                        std::fs::write(jb.join(format!("{n}.json")), b).unwrap();
                        Response::text(201, "queued")
                    }
                    Err(e) => e.response(),
                },
                _ => Response::text(404, "not found"),
            }
        })
    });
    Running { addr, stats, events, staging, jobs, _root: root }
}

/// A response: status, head, body.
struct Reply {
    status: u16,
    head: String,
    body: Vec<u8>,
}

fn parse(buf: &[u8]) -> Reply {
    let end = buf.windows(4).position(|w| w == b"\r\n\r\n").unwrap_or_else(|| panic!("no HTTP head in {:?}", String::from_utf8_lossy(buf)));
    let head = String::from_utf8_lossy(&buf[..end]).to_string();
    let status = head.split(' ').nth(1).and_then(|c| c.parse().ok()).expect("status code");
    Reply { status, head, body: buf[end + 4..].to_vec() }
}

impl Reply {
    fn content_length(&self) -> Option<usize> {
        self.head.lines().find_map(|l| l.to_ascii_lowercase().strip_prefix("content-length:").map(|v| v.trim().parse().unwrap()))
    }
}

/// Send `head` (lines without the blank line; `Connection: close` is added) and `body`; the reply.
fn exchange(addr: &str, head: &str, body: &[u8]) -> Reply {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(HANG)).unwrap();
    s.write_all(format!("{head}Connection: close\r\n\r\n").as_bytes()).unwrap();
    let _ = s.write_all(body);
    let mut buf = Vec::new();
    let _ = s.read_to_end(&mut buf);
    parse(&buf)
}

fn files_in(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    v.sort();
    v
}

/// Everything under `dir`, recursively (relative paths).
fn tree(dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            out.push(p.strip_prefix(dir).unwrap().display().to_string());
            if p.is_dir() {
                stack.push(p);
            }
        }
    }
    out.sort();
    out
}

fn wait_until(what: &str, mut f: impl FnMut() -> bool) {
    let t0 = Instant::now();
    while !f() {
        assert!(t0.elapsed() < HANG, "{what}: not within {HANG:?}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// A POST (or PUT) without the page's token, with a wrong one, with a foreign Origin or Host, or cross-site, is
/// refused before any route sees it: nothing is written. The page carries the token; with it the POST is taken.
#[test]
fn post_needs_the_token_and_the_own_origin_and_host() {
    let r = start(Opts::default());
    let a = &r.addr;
    let port = a.rsplit(':').next().unwrap();
    let page = exchange(a, &format!("GET / HTTP/1.1\r\nHost: {a}\r\n"), b"");
    assert_eq!(page.status, 200);
    assert!(String::from_utf8_lossy(&page.body).contains(&format!("<meta name=\"mvsplat360-token\" content=\"{TOKEN}\">")));
    let job = br#"{"scene":"x"}"#;
    let post = |extra: &str| exchange(a, &format!("POST /jobs HTTP/1.1\r\n{extra}Content-Length: {}\r\n", job.len()), job).status;
    let tok = format!("{TOKEN_HEADER}: {TOKEN}\r\n");
    let refused = [
        (format!("Host: {a}\r\n"), 403),
        (format!("Host: {a}\r\n{TOKEN_HEADER}: 0123456789abcdef0123456789abcdee\r\n"), 403),
        (format!("Host: {a}\r\n{TOKEN_HEADER}: {TOKEN}x\r\n"), 403),
        (format!("Host: {a}\r\n{TOKEN_HEADER}: \r\n"), 403),
        (format!("Host: {a}\r\n{tok}{tok}"), 403),
        (format!("Host: {a}\r\n{tok}Origin: http://evil.example\r\n"), 403),
        (format!("Host: {a}\r\n{tok}Origin: http://localhost:{port}\r\n"), 403),
        (format!("Host: {a}\r\n{tok}Origin: null\r\n"), 403),
        (format!("Host: {a}\r\n{tok}Sec-Fetch-Site: cross-site\r\n"), 403),
        (format!("Host: evil.example:{port}\r\n{tok}"), 403),
        (format!("Host: evil.example:{port}\r\n{tok}Origin: http://evil.example:{port}\r\n"), 403),
        (format!("Host: 127.0.0.1:1\r\n{tok}"), 403),
        (tok.clone(), 400),
        (format!("Host: {a}\r\nHost: evil.example\r\n{tok}"), 400),
    ];
    for (extra, want) in &refused {
        assert_eq!(post(extra), *want, "{extra}");
    }
    // The same for an upload.
    let put = exchange(a, &format!("PUT /upload/a.jpg HTTP/1.1\r\nHost: {a}\r\nContent-Length: 3\r\n"), b"abc");
    assert_eq!(put.status, 403);
    let put = exchange(a, &format!("PUT /upload/a.jpg HTTP/1.1\r\nHost: evil.example\r\n{tok}Content-Length: 3\r\n"), b"abc");
    assert_eq!(put.status, 403);
    assert!(tree(&r.jobs).is_empty() && tree(&r.staging).is_empty(), "a refused request wrote {:?} {:?}", tree(&r.jobs), tree(&r.staging));
    // The page's own requests: taken.
    assert_eq!(post(&format!("Host: {a}\r\n{tok}Origin: http://{a}\r\nSec-Fetch-Site: same-origin\r\n")), 201);
    assert_eq!(post(&format!("Host: localhost:{port}\r\n{tok}Origin: http://localhost:{port}\r\n")), 201);
    assert_eq!(files_in(&r.jobs), ["0.json", "1.json"]);
    assert_eq!(std::fs::read(r.jobs.join("0.json")).unwrap(), job);
    // GET needs no token.
    assert_eq!(exchange(a, &format!("GET /ping HTTP/1.1\r\nHost: {a}\r\n"), b"").status, 200);
}

/// An upload over the limit is refused with 413 and leaves nothing; a path-traversal name is refused; a body cut
/// short by the client leaves no partial file; one within the limit is stored whole.
#[test]
fn uploads_are_limited_named_plainly_and_never_left_half() {
    let max = 64u64 << 10;
    let r = start(Opts { max_upload: max, ..Opts::default() });
    let a = &r.addr;
    let tok = format!("{TOKEN_HEADER}: {TOKEN}\r\n");
    let put = |name: &str, len: usize, body: &[u8]| exchange(a, &format!("PUT /upload/{name} HTTP/1.1\r\nHost: {a}\r\n{tok}Content-Length: {len}\r\n"), body);

    // Within the limit: stored whole.
    let data: Vec<u8> = (0..max as usize).map(|i| (i % 251) as u8).collect();
    let ok = put("photo%20one.jpg", data.len(), &data);
    assert_eq!(ok.status, 201, "{}", String::from_utf8_lossy(&ok.body));
    assert_eq!(std::fs::read(r.staging.join("photo one.jpg")).unwrap(), data);
    // A name already taken is not overwritten.
    assert_eq!(put("photo%20one.jpg", 3, b"abc").status, 500);
    assert_eq!(std::fs::read(r.staging.join("photo one.jpg")).unwrap(), data);
    std::fs::remove_file(r.staging.join("photo one.jpg")).unwrap();

    // Over the limit: 413, the whole answer readable although the body was sent, and nothing written.
    let big = vec![7u8; 3 * max as usize];
    let got = put("big.jpg", big.len(), &big);
    assert_eq!(got.status, 413);
    assert_eq!(got.content_length(), Some(got.body.len()));
    assert!(tree(&r.staging).is_empty(), "{:?}", tree(&r.staging));
    // One byte over: the same.
    assert_eq!(put("big.jpg", max as usize + 1, &big[..max as usize + 1]).status, 413);
    assert!(tree(&r.staging).is_empty(), "{:?}", tree(&r.staging));

    // A body of unknown length (chunked): refused, nothing written.
    let chunked = exchange(a, &format!("PUT /upload/c.jpg HTTP/1.1\r\nHost: {a}\r\n{tok}Transfer-Encoding: chunked\r\n"), b"3\r\nabc\r\n0\r\n\r\n");
    assert_eq!(chunked.status, 411);
    assert!(tree(&r.staging).is_empty());

    // A length that could frame the body two ways: refused, nothing written.
    for lens in ["Content-Length: 3\r\nContent-Length: 3\r\n", "Content-Length: 3\r\nTransfer-Encoding: chunked\r\n"] {
        assert_eq!(exchange(a, &format!("PUT /upload/d.jpg HTTP/1.1\r\nHost: {a}\r\n{tok}{lens}"), b"abc").status, 400, "{lens}");
    }
    assert_eq!(put("e.jpg", 0, b"").status, 201, "an empty file");
    std::fs::remove_file(r.staging.join("e.jpg")).unwrap();
    assert!(tree(&r.staging).is_empty());

    // `Expect: 100-continue` (curl's way for large bodies): the body is asked for, then stored.
    let mut s = TcpStream::connect(a).unwrap();
    s.set_read_timeout(Some(HANG)).unwrap();
    write!(s, "PUT /upload/cont.jpg HTTP/1.1\r\nHost: {a}\r\n{tok}Content-Length: 3\r\nExpect: 100-continue\r\nConnection: close\r\n\r\n").unwrap();
    let mut got = String::new();
    read_until(&mut s, &mut got, "HTTP/1.1 100 Continue\r\n\r\n", Instant::now() + HANG);
    s.write_all(b"abc").unwrap();
    let mut rest = Vec::new();
    let _ = s.read_to_end(&mut rest);
    assert_eq!(parse(&rest).status, 201);
    assert_eq!(std::fs::read(r.staging.join("cont.jpg")).unwrap(), b"abc");
    std::fs::remove_file(r.staging.join("cont.jpg")).unwrap();
    // Refused before it is asked for: answered at once, the body never sent.
    let mut s = TcpStream::connect(a).unwrap();
    write!(s, "PUT /upload/cont.jpg HTTP/1.1\r\nHost: {a}\r\nContent-Length: 3\r\nExpect: 100-continue\r\n\r\n").unwrap();
    let t0 = Instant::now();
    let got = read_reply(&mut s);
    assert_eq!(got.status, 403);
    assert!(t0.elapsed() < HANG);
    assert!(tree(&r.staging).is_empty());

    // Names that are not plain: refused (the request line sent byte for byte).
    for name in [
        "..%2f..%2fevil.jpg",
        "%2e%2e%2fevil.jpg",
        "..%5cevil.jpg",
        "../evil.jpg",
        "../../evil.jpg",
        "%2e%2e",
        "..",
        ".hidden",
        "a%00.jpg",
        "sub/a.jpg",
        "%2fetc%2fpasswd",
    ] {
        let got = put(name, 3, b"abc");
        assert_eq!(got.status, 400, "{name}: {}", String::from_utf8_lossy(&got.body));
    }
    assert!(tree(&r.staging).is_empty(), "{:?}", tree(&r.staging));
    let root = r.staging.parent().unwrap().parent().unwrap();
    assert_eq!(tree(root), ["work", "work/.staging", "work/jobs"], "a name escaped the staging folder");

    // The client goes halfway: the partial file is removed.
    let mut s = TcpStream::connect(a).unwrap();
    write!(s, "PUT /upload/half.jpg HTTP/1.1\r\nHost: {a}\r\n{tok}Content-Length: {max}\r\n\r\n").unwrap();
    s.write_all(&data[..1000]).unwrap();
    wait_until("the upload started", || r.staging.join("half.jpg").exists());
    drop(s);
    wait_until("the partial file removed", || tree(&r.staging).is_empty());
    wait_until("the upload's permit returned", || r.stats.uploads() == 0);
}

/// Read a whole response from `s` (until the server closes).
fn read_reply(s: &mut TcpStream) -> Reply {
    s.set_read_timeout(Some(HANG)).unwrap();
    let mut buf = Vec::new();
    let _ = s.read_to_end(&mut buf);
    parse(&buf)
}

/// The connection cap + 1: that client reads a whole 503 — also when it sent its request (with a body) first, and
/// when it sends nothing; the held connections are served as before, and a slot freed is taken again.
#[test]
fn over_the_cap_a_client_reads_a_whole_503() {
    let cap = 4;
    let r = start(Opts { limits: Limits { connections: cap, idle: Duration::from_secs(20), ..Limits::default() }, ..Opts::default() });
    let a = &r.addr;
    let held: Vec<TcpStream> = (0..cap).map(|_| TcpStream::connect(a).unwrap()).collect();
    wait_until("the held connections counted", || r.stats.connections() == cap);
    let check = |got: Reply, what: &str| {
        assert_eq!(got.status, 503, "{what}: {}", got.head);
        assert_eq!(got.content_length(), Some(got.body.len()), "{what}: a cut answer");
        assert!(String::from_utf8_lossy(&got.body).contains("too many connections"), "{what}");
        assert!(got.head.contains("Retry-After:"), "{what}");
    };
    for _ in 0..3 {
        // A request sent whole, body and all, before reading.
        let mut s = TcpStream::connect(a).unwrap();
        let body = vec![b'x'; 20_000];
        write!(s, "POST /jobs HTTP/1.1\r\nHost: {a}\r\n{TOKEN_HEADER}: {TOKEN}\r\nContent-Length: {}\r\n\r\n", body.len()).unwrap();
        s.write_all(&body).unwrap();
        std::thread::sleep(Duration::from_millis(100));
        check(read_reply(&mut s), "after its request");
        // A plain GET.
        let mut s = TcpStream::connect(a).unwrap();
        write!(s, "GET /ping HTTP/1.1\r\nHost: {a}\r\n\r\n").unwrap();
        check(read_reply(&mut s), "after a GET");
        // Nothing sent.
        let mut s = TcpStream::connect(a).unwrap();
        check(read_reply(&mut s), "silent");
    }
    assert!(tree(&r.jobs).is_empty());
    // The held ones are served.
    for mut s in held {
        write!(s, "GET /ping HTTP/1.1\r\nHost: {a}\r\nConnection: close\r\n\r\n").unwrap();
        assert_eq!(read_reply(&mut s).status, 200);
    }
    wait_until("the slots freed", || r.stats.connections() == 0);
    assert_eq!(exchange(a, &format!("GET /ping HTTP/1.1\r\nHost: {a}\r\n"), b"").status, 200);
}

/// Read from `s` until `text` has arrived (all read so far returned); panics at the deadline.
fn read_until(s: &mut TcpStream, got: &mut String, text: &str, deadline: Instant) {
    let mut b = [0u8; 4096];
    while !got.contains(text) {
        let left = deadline.saturating_duration_since(Instant::now());
        assert!(!left.is_zero(), "{text:?} not received; got {got:?}");
        s.set_read_timeout(Some(left)).unwrap();
        match s.read(&mut b) {
            Ok(0) => panic!("closed before {text:?}; got {got:?}"),
            Ok(n) => got.push_str(&String::from_utf8_lossy(&b[..n])),
            Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {}
            Err(e) => panic!("{e}; got {got:?}"),
        }
    }
}

fn open_stream(addr: &str, last: Option<u64>) -> (TcpStream, String) {
    let mut s = TcpStream::connect(addr).unwrap();
    let resume = last.map(|id| format!("Last-Event-ID: {id}\r\n")).unwrap_or_default();
    write!(s, "GET /events HTTP/1.1\r\nHost: {addr}\r\nAccept: text/event-stream\r\n{resume}\r\n").unwrap();
    let mut got = String::new();
    read_until(&mut s, &mut got, ": stream open\n\n", Instant::now() + HANG);
    assert!(got.starts_with("HTTP/1.1 200") && got.contains("Content-Type: text/event-stream"), "{got}");
    (s, got)
}

/// Seconds to get `/ping`.
fn ping_secs(addr: &str) -> f64 {
    let t0 = Instant::now();
    assert_eq!(exchange(addr, &format!("GET /ping HTTP/1.1\r\nHost: {addr}\r\n"), b"").status, 200);
    t0.elapsed().as_secs_f64()
}

/// Seconds to open the event stream and receive an event sent on it.
fn stream_secs(r: &Running, tag: &str) -> f64 {
    let t0 = Instant::now();
    let (mut s, mut got) = open_stream(&r.addr, Some(r.events.last_id()));
    r.events.send("probe", tag);
    read_until(&mut s, &mut got, &format!("data: {tag}\n\n"), Instant::now() + HANG);
    t0.elapsed().as_secs_f64()
}

/// An upload trickling `chunk` bytes every `every` until the server answers; the answer.
fn trickle(addr: &str, name: &str, len: usize, chunk: usize, every: Duration) -> Reply {
    let mut s = TcpStream::connect(addr).unwrap();
    write!(s, "PUT /upload/{name} HTTP/1.1\r\nHost: {addr}\r\n{TOKEN_HEADER}: {TOKEN}\r\nContent-Length: {len}\r\n\r\n").unwrap();
    s.set_read_timeout(Some(every)).unwrap();
    let t0 = Instant::now();
    let mut buf = Vec::new();
    let mut b = [0u8; 4096];
    loop {
        assert!(t0.elapsed() < HANG, "a slow upload was never cut off");
        if buf.is_empty() && s.write_all(&vec![b'z'; chunk]).is_err() {
            break;
        }
        match s.read(&mut b) {
            Ok(0) => break,
            Ok(n) => buf.extend_from_slice(&b[..n]),
            Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {}
            Err(_) => break,
        }
    }
    parse(&buf)
}

/// As many slow uploads as allowed (trickling under the minimum rate) are cut off with 408 and leave no file; one
/// more at the same time is answered 503; meanwhile a page request and the event stream answer within a second
/// of their time alone.
#[test]
fn slow_uploads_are_cut_off_and_do_not_hold_the_page_or_the_stream() {
    let uploads = 3;
    let body = BodyLimits { min_rate: 1024, window: Duration::from_secs(4), uploads };
    let r = Arc::new(start(Opts { body, ..Opts::default() }));
    let ping_alone = ping_secs(&r.addr);
    let stream_alone = stream_secs(&r, "alone");

    // 200 bytes every 400 ms: 500 B/s, under the 1 KiB/s asked for.
    let slow: Vec<_> = (0..uploads)
        .map(|i| {
            let addr = r.addr.clone();
            std::thread::spawn(move || trickle(&addr, &format!("slow{i}.jpg"), 32 << 10, 200, Duration::from_millis(400)))
        })
        .collect();
    wait_until("the slow uploads under way", || r.stats.uploads() == uploads);
    // One more: refused while they run.
    let busy = exchange(&r.addr, &format!("PUT /upload/more.jpg HTTP/1.1\r\nHost: {}\r\n{TOKEN_HEADER}: {TOKEN}\r\nContent-Length: 3\r\n", r.addr), b"abc");
    assert_eq!(busy.status, 503, "{}", String::from_utf8_lossy(&busy.body));
    assert!(busy.head.contains("Retry-After:"));
    assert_eq!(r.stats.uploads(), uploads, "measured while the slow uploads run");
    let ping_during = ping_secs(&r.addr);
    let stream_during = stream_secs(&r, "during");
    assert_eq!(r.stats.uploads(), uploads, "measured while the slow uploads run");
    assert!(ping_during < ping_alone + 1.0, "a page request took {ping_during:.2} s beside slow uploads ({ping_alone:.3} s alone)");
    assert!(stream_during < stream_alone + 1.0, "the event stream took {stream_during:.2} s beside slow uploads ({stream_alone:.3} s alone)");

    for t in slow {
        let got = t.join().unwrap();
        assert_eq!(got.status, 408, "{}", String::from_utf8_lossy(&got.body));
    }
    wait_until("the partial files removed", || tree(&r.staging).is_empty());
    wait_until("the permits returned", || r.stats.uploads() == 0);
    // A fast upload is taken again.
    let ok = exchange(&r.addr, &format!("PUT /upload/fast.jpg HTTP/1.1\r\nHost: {}\r\n{TOKEN_HEADER}: {TOKEN}\r\nContent-Length: 3\r\n", r.addr), b"abc");
    assert_eq!(ok.status, 201);
}

/// A stream with no events for longer than the idle limit gets heartbeats and stays open, then delivers the next
/// event; a stream resumed with `Last-Event-ID` gets only what came after.
#[test]
fn a_silent_stream_gets_heartbeats_and_stays_open() {
    let limits = Limits { idle: Duration::from_millis(1500), head: Duration::from_millis(1500), write: Duration::from_secs(3), ..Limits::default() };
    let r = start(Opts { limits, heartbeat: Duration::from_millis(500), ..Opts::default() });
    for i in 1..=3 {
        r.events.send("progress", &format!("step {i}"));
    }
    let (mut s, mut got) = open_stream(&r.addr, None);
    read_until(&mut s, &mut got, "id: 3\nevent: progress\ndata: step 3\n\n", Instant::now() + HANG);
    assert!(got.contains("id: 1\nevent: progress\ndata: step 1\n\n"), "{got}");
    // Silent for 4 s, beyond the 1.5 s idle limit.
    let quiet_from = got.len();
    let t0 = Instant::now();
    let mut b = [0u8; 4096];
    while t0.elapsed() < Duration::from_secs(4) {
        s.set_read_timeout(Some(Duration::from_millis(200))).unwrap();
        match s.read(&mut b) {
            Ok(0) => panic!("the stream was closed after {:?} without events: {got:?}", t0.elapsed()),
            Ok(n) => got.push_str(&String::from_utf8_lossy(&b[..n])),
            Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {}
            Err(e) => panic!("{e}"),
        }
    }
    let beats = got[quiet_from..].matches(": heartbeat\n\n").count();
    assert!(beats >= 3, "{beats} heartbeats in 4 s: {:?}", &got[quiet_from..]);
    r.events.send("done", "{\"ok\":true}");
    read_until(&mut s, &mut got, "id: 4\nevent: done\ndata: {\"ok\":true}\n\n", Instant::now() + HANG);

    // A reload resumes after the last event it had.
    let (mut s2, mut got2) = open_stream(&r.addr, Some(2));
    read_until(&mut s2, &mut got2, "id: 4\n", Instant::now() + HANG);
    assert!(got2.contains("id: 3\n") && !got2.contains("id: 2\n") && !got2.contains("id: 1\n"), "{got2}");
    assert_eq!(r.events.streams(), 2);
}

/// Stream clients that vanish (sockets dropped mid-stream) free their threads and slots.
#[test]
fn a_vanished_stream_client_frees_its_slot() {
    let r = start(Opts { heartbeat: Duration::from_millis(300), ..Opts::default() });
    let streams: Vec<TcpStream> = (0..3).map(|_| open_stream(&r.addr, None).0).collect();
    wait_until("the streams counted", || r.stats.connections() == 3 && r.events.streams() == 3);
    r.events.send("progress", "1");
    drop(streams);
    wait_until("the slots freed", || r.stats.connections() == 0 && r.events.streams() == 0);
}

/// A port in use is an error naming it and `--port`; port 0 is any free one.
#[test]
fn a_port_in_use_is_named() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = taken.local_addr().unwrap().port();
    let e = HttpServer::bind("127.0.0.1", port).err().expect("bound a port in use").to_string();
    assert!(e.contains(&port.to_string()) && e.contains("--port") && !e.contains('\n'), "{e}");
    let any = HttpServer::bind("127.0.0.1", 0).unwrap();
    assert_ne!(any.port(), 0);
    assert!(any.url().ends_with(&format!(":{}/", any.port())));
    assert_ne!(mvsplat360_viewer::APP_PORT, mvsplat360_viewer::VIEW_PORT);
}
