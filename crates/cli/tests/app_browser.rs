//! `mvsplat360 app` in a real browser: headless Chromium (Debian's `chromium`, WebGL on SwiftShader) opens the
//! page, uploads the bundled scene (`assets/woodbox`: photos + `transforms.json`) through the file input (files set
//! over the DevTools protocol), starts a job (shipped model, 4 orbit frames, no refiner) and sees its progress
//! advance over the event stream; the job is held by the test hook (`MVSPLAT360_HOLD_AT`) at a stage: a reload
//! picks the job and its progress up again; cancel from the page ends its process group and leaves no half result;
//! with the hold lifted, resume from the page finishes it, and the result shows in the viewer with a non-blank 3D
//! canvas. Screenshots (the page mid-job and done; docs/images/app-*.png are these, quantised) land in `$CARGO_TARGET_TMPDIR/app-test/`.
//!
//! Without Chromium this test fails (it does not skip): `apt-get install -y chromium`, or set `CHROMIUM`.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use headless_chrome::browser::tab::Tab;
use headless_chrome::protocol::cdp::Page;

mod browser;
use browser::{chromium, eval, launch, watch_console};

mod served;
use served::{root, Killed};

fn serve_app(work: &Path, hold: &Path) -> (Killed, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_mvsplat360"))
        .args(["app", "--port", "0", "--workdir"])
        .arg(work)
        .env("MVSPLAT360_HOLD_AT", "fitting")
        .env("MVSPLAT360_HOLD_WHILE", hold)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let url = line.split_whitespace().find(|w| w.starts_with("http://127.0.0.1:")).unwrap_or_else(|| panic!("no address in {line:?}"));
    (Killed(child), url.to_string())
}

/// Wait until `expr` is true (at most `secs`), naming `what` when it never is.
fn wait_for(tab: &Tab, expr: &str, secs: u64, what: &str, log: &Mutex<Vec<String>>) {
    let t0 = Instant::now();
    while eval(tab, expr) != serde_json::Value::Bool(true) {
        let page = eval(tab, "({state: document.getElementById('job-state').textContent, upload: document.getElementById('upload-status').textContent, error: document.getElementById('error-line').textContent, log: document.getElementById('log').textContent.slice(-2000)})");
        assert!(t0.elapsed() < Duration::from_secs(secs), "{what}: not within {secs} s; page: {page}\nconsole:\n{}", log.lock().unwrap().join("\n"));
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn wait_ready(tab: &Tab, url: &str, log: &Mutex<Vec<String>>) {
    tab.navigate_to(url).unwrap().wait_until_navigated().unwrap();
    wait_for(tab, "!!(window.mvsplat360app && window.mvsplat360app.ready)", 30, "page ready", log);
}

/// The page (or the element `selector`) as a PNG, scaled to `width` pixels.
fn shot(tab: &Tab, selector: Option<&str>, width: u32) -> image::RgbImage {
    let clip = selector.map(|sel| {
        let r = eval(
            tab,
            &format!("(() => {{ const e = {sel}; const r = e.getBoundingClientRect(); return [r.x + scrollX, r.y + scrollY, r.width, r.height]; }})()"),
        );
        let v: Vec<f64> = serde_json::from_value(r).unwrap();
        Page::Viewport { x: v[0], y: v[1], width: v[2], height: v[3], scale: 1.0 }
    });
    let png = tab.capture_screenshot(Page::CaptureScreenshotFormatOption::Png, None, clip, true).unwrap();
    let img = image::load_from_memory(&png).unwrap().to_rgb8();
    let h = (img.height() as f64 * width as f64 / img.width() as f64).round() as u32;
    image::imageops::resize(&img, width, h.max(1), image::imageops::FilterType::Triangle)
}

fn std_dev(img: &image::RgbImage) -> f64 {
    let v: Vec<f64> = img.pixels().map(|p| (0.299 * p[0] as f64 + 0.587 * p[1] as f64 + 0.114 * p[2] as f64) / 255.0).collect();
    let m = v.iter().sum::<f64>() / v.len() as f64;
    (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64).sqrt()
}

fn group_alive(pid: i32) -> bool {
    // SAFETY: signal 0 checks only.
    unsafe { libc::kill(-pid, 0) == 0 }
}

#[test]
fn app_page_in_headless_chromium() {
    let chrome = chromium();
    let t_all = Instant::now();
    let tmp = tempfile::tempdir().unwrap();
    let (work, hold) = (tmp.path().join("work"), tmp.path().join("hold"));
    std::fs::write(&hold, b"").unwrap();
    let shots = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("app-test");
    std::fs::create_dir_all(&shots).unwrap();
    let (_app, url) = serve_app(&work, &hold);
    let (browser, _profile) = launch(&chrome, &[]);
    let tab = browser.new_tab().unwrap();
    let (errors, log) = watch_console(&tab);
    wait_ready(&tab, &url, &log);

    // The scene through the file input, as a person picking the files would.
    let scene = root().join("assets/woodbox");
    let mut files = vec![scene.join("transforms.json")];
    files.extend(std::fs::read_dir(scene.join("images")).unwrap().map(|e| e.unwrap().path()));
    let names: Vec<String> = files.iter().map(|p| p.canonicalize().unwrap().display().to_string()).collect();
    let refs: Vec<&str> = names.iter().map(String::as_str).collect();
    eval(
        &tab,
        "(() => { const s = {orbit_frames: 4, refiner_steps: 0, device: 'cpu'}; for (const k in s) document.getElementById(k).value = s[k]; return true; })()",
    );
    tab.find_element("#files").unwrap().set_input_files(&refs).unwrap();
    let n = files.len();
    wait_for(&tab, &format!("window.mvsplat360app.uploaded === {n} && !window.mvsplat360app.uploading"), 30, "upload", &log);
    eval(&tab, "(() => { document.getElementById('start').click(); return true; })()");

    // Progress over the event stream until the hook holds the job.
    let held = "(() => { const a = window.mvsplat360app, j = a.jobs[a.selected]; return !!j && j.state === 'running' && j.stages.length > 0 && j.stages[j.stages.length - 1].name === 'fitting'; })()";
    wait_for(&tab, held, 120, "the job held at its stage", &log);
    let seen = eval(&tab, "({events: window.mvsplat360app.events, rows: document.querySelectorAll('#stages .stage').length, full: [...document.querySelectorAll('#stages progress')].filter(p => p.max > 0 && p.value === p.max).length})");
    assert!(seen["events"].as_u64() > Some(3) && seen["rows"].as_u64() >= Some(3) && seen["full"].as_u64() >= Some(1), "{seen}");
    shot(&tab, None, 760).save(shots.join("app-running.png")).unwrap();

    // A reload picks the running job and its progress up again.
    wait_ready(&tab, &url, &log);
    wait_for(&tab, held, 10, "the held job after a reload", &log);
    let after = eval(&tab, "({state: document.getElementById('job-state').textContent, rows: document.querySelectorAll('#stages .stage').length, log: document.getElementById('log').textContent.length})");
    assert_eq!(after["state"], "running", "{after}");
    assert!(after["rows"].as_u64() >= seen["rows"].as_u64() && after["log"].as_u64() > Some(0), "{after}");
    let id = eval(&tab, "window.mvsplat360app.selected").as_str().unwrap().to_string();
    let pid = eval(&tab, "window.mvsplat360app.jobs[window.mvsplat360app.selected].pid").as_i64().unwrap() as i32;

    // Cancel from the page: the group is gone, no half result.
    eval(&tab, "(() => { document.getElementById('cancel').click(); return true; })()");
    wait_for(&tab, "document.getElementById('job-state').textContent === 'cancelled'", 30, "cancelled", &log);
    assert!(!group_alive(pid), "the job's process group outlived its cancel");
    let out = work.join("jobs").join(&id).join("out");
    for f in ["gaussians.ply", "run.json", "cameras.json", "video.mp4"] {
        assert!(!out.join(f).exists(), "a cancelled job left {f}");
    }

    // The hold lifted, resume from the page: done, the result in the viewer.
    std::fs::remove_file(&hold).unwrap();
    eval(&tab, "(() => { document.getElementById('resume').click(); return true; })()");
    let events = seen["events"].as_u64().unwrap();
    wait_for(&tab, &format!("window.mvsplat360app.events > {events} + 5"), 60, "progress of the resumed job", &log);
    wait_for(&tab, "document.getElementById('job-state').textContent === 'done'", 120, "done", &log);
    let viewer = "document.getElementById('viewer')";
    wait_for(&tab, &format!("!!({viewer}.contentWindow.mvsplat360 && {viewer}.contentWindow.mvsplat360.ready)"), 60, "the viewer ready", &log);
    eval(&tab, &format!("(() => {{ {viewer}.scrollIntoView(); return true; }})()"));
    let canvas = shot(
        &tab,
        Some(&format!("(() => {{ const f = {viewer}, c = f.contentDocument.getElementById('canvas3d'), a = f.getBoundingClientRect(), b = c.getBoundingClientRect(); return {{getBoundingClientRect: () => ({{x: a.x + b.x, y: a.y + b.y, width: b.width, height: b.height}})}}; }})()")),
        256,
    );
    assert!(std_dev(&canvas) > 0.03, "the 3D canvas is blank (luma std {:.4})", std_dev(&canvas));
    eval(&tab, "(() => { window.scrollTo(0, 0); return true; })()");
    shot(&tab, None, 760).save(shots.join("app-done.png")).unwrap();
    let errs: Vec<String> = errors.lock().unwrap().iter().filter(|e| !e.contains("favicon")).cloned().collect();
    assert!(errs.is_empty(), "console errors: {errs:?}");
    eprintln!("app page test: {:.1} s; screenshots in {}", t_all.elapsed().as_secs_f64(), shots.display());
}
