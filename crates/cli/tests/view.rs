//! `mvsplat360 view` in a real browser: headless Chromium (Debian's `chromium`, WebGL on SwiftShader) loads the
//! page served for a small render of the bundled scene (shipped model, 128×64, `--refiner none`) and checks:
//! no console errors; the OpenCV → three.js camera conversion of the bundle against the pinhole formula; the 3D
//! canvas is not blank; the view from target 0 resembles `frames/gsplat/0000.png` (our rasterizer's image of the
//! same Gaussians) better than any other target's frame; the frame slider changes the images shown; the parts
//! without data (refined frames) are hidden; the 3D panel's loading line goes fetching → decoding → sorting → done
//! and is hidden at the end; the metrics table has a row per scored frame set. Then a second Chromium without
//! WebGL2 (`--disable-webgl2`: a real absence, nothing in the page is faked) gets the page's one-line notice, no 3D
//! view and no Gaussians download, and the frames and run info still show. Screenshots land in
//! `$CARGO_TARGET_TMPDIR/view-test/`.
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

fn render(out: &Path) {
    let t = Instant::now();
    let o = Command::new(env!("CARGO_BIN_EXE_mvsplat360"))
        .args(["--quiet", "render"])
        .arg(root().join("assets/woodbox"))
        .arg("--ckpt")
        .arg(root().join("assets/models/default"))
        .args(["--size", "128x64", "--context", "0,5,10,15,19", "--targets", "2,8,13,22", "--fit-steps", "2", "--no-metrics", "--out"])
        .arg(out)
        .output()
        .unwrap();
    assert!(o.status.success(), "render failed: {}", String::from_utf8_lossy(&o.stderr));
    eprintln!("render: {:.1} s", t.elapsed().as_secs_f64());
}

fn serve(out: &Path) -> (Killed, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_mvsplat360"))
        .arg("view")
        .arg(out)
        .args(["--port", "0"])
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let url = line.split_whitespace().find(|w| w.starts_with("http://127.0.0.1:")).unwrap_or_else(|| panic!("no address in {line:?}"));
    (Killed(child), url.to_string())
}

/// Open `url` and wait until the page says it is ready (or shows an error: that fails the test).
fn open_page(tab: &Tab, url: &str, log: &Mutex<Vec<String>>) -> Duration {
    let t0 = Instant::now();
    tab.navigate_to(url).unwrap().wait_until_navigated().unwrap();
    loop {
        let state = eval(tab, "({ ready: !!(window.mvsplat360 && window.mvsplat360.ready), error: document.getElementById('error').hidden ? null : document.getElementById('error').textContent })");
        if let Some(e) = state["error"].as_str() {
            panic!("the page reports: {e}\nconsole:\n{}", log.lock().unwrap().join("\n"));
        }
        if state["ready"] == true {
            return t0.elapsed();
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "page not ready after 60 s; console:\n{}", log.lock().unwrap().join("\n"));
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// The metrics table's rows, header first, as the cells' text.
const METRICS_ROWS: &str = "[...document.querySelectorAll('#metrics-table tr')].map(tr => [...tr.cells].map(c => c.textContent))";

fn screenshot(tab: &Tab, selector: &str) -> image::RgbImage {
    let r = eval(tab, &format!("(() => {{ const e = document.querySelector('{selector}'); e.scrollIntoView(); const r = e.getBoundingClientRect(); return [r.x + scrollX, r.y + scrollY, r.width, r.height]; }})()"));
    let v: Vec<f64> = serde_json::from_value(r).unwrap();
    let clip = Page::Viewport { x: v[0], y: v[1], width: v[2], height: v[3], scale: 1.0 };
    let png = tab.capture_screenshot(Page::CaptureScreenshotFormatOption::Png, None, Some(clip), true).unwrap();
    image::load_from_memory(&png).unwrap().to_rgb8()
}

fn luma(img: &image::RgbImage) -> Vec<f64> {
    img.pixels().map(|p| (0.299 * p[0] as f64 + 0.587 * p[1] as f64 + 0.114 * p[2] as f64) / 255.0).collect()
}

fn std_dev(v: &[f64]) -> f64 {
    let m = v.iter().sum::<f64>() / v.len() as f64;
    (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64).sqrt()
}

/// Pearson correlation of the luminance of two equally sized images.
fn correlation(a: &image::RgbImage, b: &image::RgbImage) -> f64 {
    let (x, y) = (luma(a), luma(b));
    let (mx, my) = (x.iter().sum::<f64>() / x.len() as f64, y.iter().sum::<f64>() / y.len() as f64);
    let cov: f64 = x.iter().zip(&y).map(|(a, b)| (a - mx) * (b - my)).sum();
    cov / (x.iter().map(|a| (a - mx).powi(2)).sum::<f64>() * y.iter().map(|b| (b - my).powi(2)).sum::<f64>()).sqrt()
}

fn psnr(a: &image::RgbImage, b: &image::RgbImage) -> f64 {
    let mse: f64 = a.as_raw().iter().zip(b.as_raw()).map(|(x, y)| ((*x as f64 - *y as f64) / 255.0).powi(2)).sum::<f64>() / a.as_raw().len() as f64;
    -10.0 * mse.log10()
}

fn mean_abs_diff(a: &image::RgbImage, b: &image::RgbImage) -> f64 {
    assert_eq!(a.dimensions(), b.dimensions());
    a.as_raw().iter().zip(b.as_raw()).map(|(x, y)| (*x as f64 - *y as f64).abs()).sum::<f64>() / a.as_raw().len() as f64 / 255.0
}

#[test]
fn view_page_in_headless_chromium() {
    let chrome = chromium();
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    render(&out);
    assert!(!out.join("frames/refined").exists(), "--refiner none render has no refined frames");
    // metrics.json as `render --metrics` writes it with a refiner (the real one needs the metric networks): the
    // refined frames' score (the paper's) at the top level, the histogram-matched final frames' nested under "final".
    std::fs::write(
        out.join("metrics.json"),
        r#"{"frames": "refined", "psnr": 12.5, "ssim": 0.41, "lpips": 0.2, "dists": null, "fid": 85.5, "fid_variant": "pytorch-fid", "per_image": [],
            "final": {"frames": "final", "psnr": 11.25, "ssim": 0.375, "lpips": 0.25, "dists": null, "fid": 91.25, "fid_variant": "pytorch-fid", "per_image": []}}"#,
    )
    .unwrap();
    let (_server, url) = serve(&out);
    let shots = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("view-test");
    std::fs::create_dir_all(&shots).unwrap();

    let (browser, _profile) = launch(&chrome, &[]);
    let tab = browser.new_tab().unwrap();
    tab.set_default_timeout(Duration::from_secs(60));
    let (errors, log) = watch_console(&tab);
    let page_ready = open_page(&tab, &url, &log);
    let in_page_ms = eval(&tab, "mvsplat360.loadMs").as_f64().unwrap();
    eprintln!("page ready {:.2} s after navigation (script: {:.0} ms)", page_ready.as_secs_f64(), in_page_ms);

    // The 3D panel's loading line: each state once, in order, and hidden at the end. The download was counted
    // chunk by chunk against the Content-Length the server sends: all of gaussians.ply.
    let status: Vec<serde_json::Value> = serde_json::from_value(eval(&tab, "mvsplat360.status")).unwrap();
    eprintln!("loading states: {status:?}");
    let states: Vec<&str> = status.iter().map(|s| s["state"].as_str().unwrap()).collect();
    assert_eq!(states, ["fetching", "decoding", "sorting", "done"], "loading states out of order: {status:?}");
    let ms: Vec<f64> = status.iter().map(|s| s["ms"].as_f64().unwrap()).collect();
    assert!(ms.windows(2).all(|w| w[0] <= w[1]), "loading states' times go backwards: {ms:?}");
    for (s, word) in status.iter().zip(["fetching", "decoding", "sorting"]) {
        assert!(s["text"].as_str().unwrap().contains(word), "the line shown while {word} says {:?}", s["text"]);
    }
    let ply = std::fs::metadata(out.join("gaussians.ply")).unwrap().len();
    assert_eq!(
        (status[1]["bytes"].as_u64(), status[1]["total"].as_u64()),
        (Some(ply), Some(ply)),
        "bytes received / Content-Length of a {ply}-byte gaussians.ply"
    );
    let hidden = eval(&tab, "['status3d', 'no-webgl2', 'view3d', 'frame-3d'].map(id => document.getElementById(id).hidden)");
    assert_eq!(hidden, serde_json::json!([true, true, false, false]), "hidden: loading line, no-WebGL2 notice, 3D view, its button");

    // The camera conversion in the bundle (three.js pose + projection) against the pinhole formula
    // u = fx·x/z + cx, v = fy·y/z + cy on points given in target 0's OpenCV camera frame.
    let cams: Vec<serde_json::Value> = serde_json::from_value(eval(&tab, "mvsplat360.cameras")).unwrap();
    let t0cam = cams.iter().find(|c| c["role"] == "target").unwrap();
    let c2w: [[f64; 4]; 4] = serde_json::from_value(t0cam["c2w"].clone()).unwrap();
    let k: [[f64; 3]; 3] = serde_json::from_value(t0cam["K"].clone()).unwrap();
    for pc in [[0.0, 0.0, 3.0], [0.4, -0.3, 2.0], [-1.5, 0.7, 6.0], [2.0, 1.0, 9.0]] {
        let pw: Vec<f64> = (0..3).map(|r| c2w[r][3] + (0..3).map(|j| c2w[r][j] * pc[j]).sum::<f64>()).collect();
        let want = [k[0][0] * pc[0] / pc[2] + k[0][2], k[1][1] * pc[1] / pc[2] + k[1][2]];
        let idx = cams.iter().position(|c| std::ptr::eq(c, t0cam)).unwrap();
        let got: Vec<f64> = serde_json::from_value(eval(&tab, &format!("mvsplat360.cvToThree.projectWithThree(mvsplat360.cameras[{idx}], {pw:?})"))).unwrap();
        assert!((got[0] - want[0]).abs() < 1e-3 && (got[1] - want[1]).abs() < 1e-3, "camera-frame point {pc:?}: three.js gives {got:?}, pinhole {want:?}");
    }

    // The view from target 0 (where the page starts) against our rasterizer's frame of the same Gaussians.
    eval(&tab, "mvsplat360.setView('target', 0)");
    eval(&tab, "mvsplat360.settle()");
    let canvas = screenshot(&tab, "#canvas3d");
    canvas.save(shots.join("canvas-target0.png")).unwrap();
    let s = std_dev(&luma(&canvas));
    assert!(s > 0.03, "the 3D canvas looks blank (luminance std {s:.4})");
    let frames = ["0000", "0001", "0002", "0003"].map(|f| image::open(out.join(format!("frames/gsplat/{f}.png"))).unwrap().to_rgb8());
    let (w, h) = frames[0].dimensions();
    let small = image::imageops::resize(&canvas, w, h, image::imageops::FilterType::Triangle);
    small.save(shots.join("canvas-target0-small.png")).unwrap();
    let corr: Vec<f64> = frames.iter().map(|f| correlation(&small, f)).collect();
    let ps: Vec<f64> = frames.iter().map(|f| psnr(&small, f)).collect();
    eprintln!("view from target 0 vs frames/gsplat/000k.png: correlation {corr:.3?}, PSNR {ps:.1?} dB");
    // Wrong conversions (y or x not flipped) give the frame upside down or mirrored: they must match worse.
    let flips = [image::imageops::flip_vertical(&frames[0]), image::imageops::flip_horizontal(&frames[0])];
    let flip_corr: Vec<f64> = flips.iter().map(|f| correlation(&small, f)).collect();
    eprintln!("… vs frame 0 flipped upside down / mirrored: correlation {flip_corr:.3?}");
    // Two renderers of the same Gaussians differ (Spark blends every splat at screen resolution, sorts per splat
    // and clips at √8 σ; ours rasterizes 128×64 in tiles), so "resembles" is a correlation bound: measured
    // 0.73–0.86 for each target against its own frame, at most 0.31 against other targets' frames and at most
    // 0.47 against flipped frames (what a wrong axis conversion gives). Required: > 0.6 and 0.2 above the rest.
    assert!(corr[0] > 0.6, "view from target 0 does not resemble frames/gsplat/0000.png (correlation {:.3})", corr[0]);
    for (i, c) in corr.iter().enumerate().skip(1) {
        assert!(corr[0] > c + 0.2, "view from target 0 matches frame {i} ({c:.3}) about as well as frame 0 ({:.3})", corr[0]);
    }
    for c in &flip_corr {
        assert!(corr[0] > c + 0.2, "view from target 0 matches a flipped frame 0 ({c:.3}) about as well as frame 0 ({:.3})", corr[0]);
    }

    // Another camera button moves the view.
    eval(&tab, "mvsplat360.setView('context', 0)");
    eval(&tab, "mvsplat360.settle()");
    let ctx = screenshot(&tab, "#canvas3d");
    ctx.save(shots.join("canvas-context0.png")).unwrap();
    assert!(mean_abs_diff(&ctx, &canvas) > 0.01, "the view did not change for context camera 0");

    // Frames: refined is missing, so only gsplat / final / GT are shown; the slider changes what is shown.
    let kinds: Vec<String> = serde_json::from_value(eval(&tab, "[...document.querySelectorAll('#frames-grid figcaption')].map(e => e.textContent)")).unwrap();
    assert_eq!(kinds, ["3DGS (gsplat)", "final", "ground truth"]);
    let wait_images = "Promise.all([...document.querySelectorAll('#frames-grid img')].map(i => i.decode())).then(() => true)";
    eval(&tab, wait_images);
    let before = screenshot(&tab, "#frames-grid");
    tab.find_element("#frame").unwrap().focus().unwrap();
    tab.press_key("ArrowRight").unwrap();
    eval(&tab, wait_images);
    let after = screenshot(&tab, "#frames-grid");
    assert_eq!(eval(&tab, "document.getElementById('frame').value"), "1");
    let d = mean_abs_diff(&before, &after);
    assert!(d > 0.01, "moving the frame slider did not change the images (mean abs diff {d:.4})");
    before.save(shots.join("frames-0.png")).unwrap();
    after.save(shots.join("frames-1.png")).unwrap();

    // Run info: settings, stage times, metrics.
    let info = eval(&tab, "document.getElementById('info').innerText");
    let info = info.as_str().unwrap();
    for want in ["Settings", "Stage times", "encoder", "Metrics", "PSNR", "12.50", "pytorch-fid"] {
        assert!(info.contains(want), "run panel lacks {want:?}:\n{info}");
    }
    let rows: Vec<Vec<String>> = serde_json::from_value(eval(&tab, METRICS_ROWS)).unwrap();
    assert_eq!(
        rows,
        [
            vec!["", "PSNR", "SSIM", "LPIPS", "DISTS", "FID"],
            vec!["refined vs ground truth", "12.50", "0.4100", "0.2000", "—", "85.50"],
            vec!["final vs ground truth", "11.25", "0.3750", "0.2500", "—", "91.25"],
        ]
    );
    assert_eq!(eval(&tab, "document.getElementById('video-section').hidden"), false);

    let page = tab.capture_screenshot(Page::CaptureScreenshotFormatOption::Png, None, None, true).unwrap();
    std::fs::write(shots.join("page.png"), page).unwrap();
    eprintln!("screenshots in {}", shots.display());
    {
        let errors = errors.lock().unwrap();
        assert!(errors.is_empty(), "console errors:\n{}\nfull console:\n{}", errors.join("\n"), log.lock().unwrap().join("\n"));
    }
    drop(tab);
    drop(browser);

    // A browser without WebGL2. Also a metrics.json from before the `frames` key: it scored the final frames.
    std::fs::write(out.join("metrics.json"), r#"{"psnr": 12.5, "ssim": 0.41, "lpips": null, "dists": null, "fid": null, "per_image": []}"#).unwrap();
    let (browser, _profile) = launch(&chrome, &["--disable-webgl2"]);
    let tab = browser.new_tab().unwrap();
    tab.set_default_timeout(Duration::from_secs(60));
    let (errors, log) = watch_console(&tab);
    let page_ready = open_page(&tab, &url, &log);
    eprintln!("without WebGL2: page ready {:.2} s after navigation", page_ready.as_secs_f64());
    assert_eq!(eval(&tab, "!!document.createElement('canvas').getContext('webgl2')"), false, "Chromium ignored --disable-webgl2");
    assert_eq!(eval(&tab, "document.body.dataset.ready"), "1");
    assert_eq!(eval(&tab, "mvsplat360.status.map(s => s.state)"), serde_json::json!(["no-webgl2"]));
    let notice = eval(&tab, "document.getElementById('no-webgl2').innerText");
    let notice = notice.as_str().unwrap();
    for want in ["WebGL2", "hardware", "Chrome, Firefox or Safari", "frames"] {
        assert!(notice.contains(want), "the no-WebGL2 notice lacks {want:?}: {notice:?}");
    }
    let hidden = eval(&tab, "['no-webgl2', 'status3d', 'view3d', 'frame-3d', 'frames-section', 'video-section'].map(id => document.getElementById(id).hidden)");
    assert_eq!(hidden, serde_json::json!([false, true, true, true, false, false]), "hidden: notice, loading line, 3D view, its button, frames, video");
    // The frames load; the Gaussians, which nothing could show, are not downloaded.
    eval(&tab, wait_images);
    let widths: Vec<u32> = serde_json::from_value(eval(&tab, "[...document.querySelectorAll('#frames-grid img')].map(i => i.naturalWidth)")).unwrap();
    assert_eq!(widths, [128, 128, 128]);
    assert_eq!(eval(&tab, "performance.getEntriesByType('resource').some(e => e.name.endsWith('.ply'))"), false, "fetched the Gaussians without WebGL2");
    let rows: Vec<Vec<String>> = serde_json::from_value(eval(&tab, METRICS_ROWS)).unwrap();
    assert_eq!(rows[1..], [vec!["final vs ground truth", "12.50", "0.4100", "—", "—", "—"]]);
    let page = tab.capture_screenshot(Page::CaptureScreenshotFormatOption::Png, None, None, true).unwrap();
    std::fs::write(shots.join("page-no-webgl2.png"), page).unwrap();
    let errors = errors.lock().unwrap();
    assert!(errors.is_empty(), "console errors without WebGL2:\n{}\nfull console:\n{}", errors.join("\n"), log.lock().unwrap().join("\n"));
}

#[test]
fn incomplete_folder_is_one_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    std::fs::write(tmp.path().join("gaussians.ply"), b"ply\n").unwrap();
    std::fs::write(tmp.path().join("run.json"), b"{}").unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_mvsplat360")).arg("view").arg(tmp.path()).args(["--port", "0"]).output().unwrap();
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(err.contains("cameras.json is missing"), "{err}");
}
