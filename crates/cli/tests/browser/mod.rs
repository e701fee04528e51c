//! Headless Chromium for the page tests (`view.rs`, `app_browser.rs`): finding the browser, launching it on this
//! closed network with WebGL on SwiftShader, evaluating script and collecting the console.

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use headless_chrome::browser::tab::Tab;
use headless_chrome::protocol::cdp::types::Event;
use headless_chrome::{Browser, LaunchOptions};

pub fn chromium() -> PathBuf {
    let p = std::env::var_os("CHROMIUM").map(PathBuf::from).unwrap_or_else(|| PathBuf::from("/usr/bin/chromium"));
    assert!(
        p.is_file(),
        "headless Chromium not found at {} — this test needs a real browser: `apt-get install -y chromium` \
         (Debian), or set CHROMIUM to a Chromium/Chrome binary",
        p.display()
    );
    p
}

/// Evaluate `expr` (awaiting a promise) and return its JSON value.
pub fn eval(tab: &Tab, expr: &str) -> serde_json::Value {
    let wrapped = format!("(async () => JSON.stringify((await ({expr})) ?? null))()");
    let r = tab.evaluate(&wrapped, true).unwrap_or_else(|e| panic!("evaluating {expr}: {e}"));
    match r.value {
        Some(serde_json::Value::String(s)) => serde_json::from_str(&s).unwrap(),
        other => panic!("evaluating {expr}: no JSON result ({other:?}, {:?})", r.description),
    }
}

/// Headless Chromium with `extra` flags; the profile folder must outlive the browser.
pub fn launch(chrome: &Path, extra: &[&str]) -> (Browser, tempfile::TempDir) {
    let profile = tempfile::tempdir().unwrap();
    // Chromium hangs on this closed network without these; SwiftShader gives WebGL without a GPU.
    let args: Vec<&OsStr> = [
        "--disable-quic",
        "--disable-component-update",
        "--disable-background-networking",
        "--disable-sync",
        "--no-first-run",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--force-device-scale-factor=1",
        "--hide-scrollbars",
    ]
    .iter()
    .chain(extra)
    .map(OsStr::new)
    .collect();
    let browser = Browser::new(
        LaunchOptions::default_builder()
            .path(Some(chrome.to_path_buf()))
            .headless(true)
            .sandbox(false)
            .window_size(Some((1300, 1400)))
            .user_data_dir(Some(profile.path().to_path_buf()))
            .idle_browser_timeout(Duration::from_secs(120))
            .args(args)
            .build()
            .unwrap(),
    )
    .expect("launching headless Chromium");
    (browser, profile)
}

/// The tab's console: (errors and exceptions, every line).
pub type Console = (Arc<Mutex<Vec<String>>>, Arc<Mutex<Vec<String>>>);

pub fn watch_console(tab: &Tab) -> Console {
    let errors: Arc<Mutex<Vec<String>>> = Arc::default();
    let log: Arc<Mutex<Vec<String>>> = Arc::default();
    let (e, l) = (errors.clone(), log.clone());
    tab.enable_log().unwrap().enable_runtime().unwrap();
    tab.add_event_listener(Arc::new(move |ev: &Event| {
        let (level, text) = match ev {
            Event::RuntimeConsoleAPICalled(e) => {
                let text: Vec<String> =
                    e.params.args.iter().map(|a| a.value.as_ref().map(|v| v.to_string()).or(a.description.clone()).unwrap_or_default()).collect();
                (format!("{:?}", e.params.Type).to_lowercase(), text.join(" "))
            }
            Event::RuntimeExceptionThrown(e) => {
                let d = &e.params.exception_details;
                ("exception".to_string(), format!("{} {}", d.text, d.exception.as_ref().and_then(|x| x.description.clone()).unwrap_or_default()))
            }
            Event::LogEntryAdded(e) => {
                (format!("{:?}", e.params.entry.level).to_lowercase(), format!("{} {}", e.params.entry.text, e.params.entry.url.clone().unwrap_or_default()))
            }
            _ => return,
        };
        l.lock().unwrap().push(format!("[{level}] {text}"));
        if level == "error" || level == "exception" {
            e.lock().unwrap().push(format!("[{level}] {text}"));
        }
    }))
    .unwrap();
    (errors, log)
}
